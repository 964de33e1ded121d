"""Gated optimal assignment of points to tracks, and the rigid-partner signature that screens it."""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy.optimize import linear_sum_assignment

from mocapflow.mocap.labelling.config import VETO


def norm(v: np.ndarray) -> np.ndarray:
    """Euclidean norm over the last axis (NaN in, NaN out), cheaper than ``np.linalg.norm`` on small batches."""
    return np.sqrt(np.einsum("...i,...i->...", v, v))


def gated_cost(pred: np.ndarray, gate: np.ndarray | float, points: np.ndarray) -> np.ndarray:
    """Cost ``(A, B)`` of giving each point to each track: ``d / gate - 1`` inside the track's gate, 0 outside.

    ``pred`` is ``(A, 3)``, or ``(A, H, 3)`` for tracks with several hypotheses (NaN where absent) of which the best
    counts; ``gate`` is ``(A,)`` or ``(A, H)``, or one for all. With 0 for "unmatched" this is the classic assignment
    with a dummy option costing half a gate on each side, so a match is made only when it lowers the total distance.
    A track with no hypothesis (NaN) fits no point. Compiled: the labeller asks for it several times a frame.
    """
    hypotheses = np.ascontiguousarray(pred, dtype=np.float64)  # one compiled layout, whatever slice is passed
    if hypotheses.ndim == 2:
        hypotheses = hypotheses[:, None]
    gates = np.asarray(gate, dtype=np.float64)
    if gates.ndim < 2:  # one gate per track, or one for all
        per_hypothesis = np.empty(hypotheses.shape[:2])
        per_hypothesis[:] = gates[:, None] if gates.ndim else gates
        gates = per_hypothesis
    return gated_cost_compiled(hypotheses, gates, np.asarray(points, dtype=np.float64))


@njit(cache=True)
def distance(p: np.ndarray, q: np.ndarray) -> float:  # pragma: no cover
    """The distance between two points (3,), NaN if either is missing."""
    s = 0.0
    for c in range(3):
        d = p[c] - q[c]
        s += d * d
    return np.sqrt(s)


@njit(cache=True)
def gated_cost_compiled(pred: np.ndarray, gate: np.ndarray, points: np.ndarray) -> np.ndarray:  # pragma: no cover
    """``gated_cost`` on ``(A, H, 3)`` hypotheses and ``(A, H)`` gates, for compiled callers: each hypothesis against
    every point, the best of a track's hypotheses kept in place."""
    cost = np.zeros((pred.shape[0], len(points)))
    for a in range(pred.shape[0]):
        for h in range(pred.shape[1]):
            reach, x = gate[a, h], pred[a, h, 0]
            for b in range(len(points)):
                if abs(x - points[b, 0]) >= reach:  # as far along x alone: outside the gate
                    continue
                inside = distance(pred[a, h], points[b]) / reach - 1.0
                if inside < cost[a, b]:  # within the gate, and nearer than another hypothesis; NaN never is
                    cost[a, b] = inside
    return cost


def match(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Optimal one-to-one assignment on a cost matrix where only negative entries are admissible pairs.

    Two common cases are answered without the solver's fixed cost. With one track or one point the optimum is the
    single cheapest pair (the first of equal ones, as ``linear_sum_assignment`` picks). When no row and no column
    holds two admissible entries (every track near its own point and no other, most frames) the optimum is all of
    them: leaving one out could only raise the total.
    """
    if cost.size == 0:
        return np.empty(0, np.intp), np.empty(0, np.intp)
    if cost.shape[0] == 1 or cost.shape[1] == 1:
        best = int(cost.argmin())
        if not cost.flat[best] < 0.0:
            return np.empty(0, np.intp), np.empty(0, np.intp)
        pair = np.zeros(1, np.intp), np.array([best], np.intp)
        return pair if cost.shape[0] == 1 else pair[::-1]
    rows, cols, unique = unambiguous(cost)
    if unique:
        return rows, cols
    rows, cols = linear_sum_assignment(cost)
    keep = cost[rows, cols] < 0.0
    return rows[keep], cols[keep]


@njit(cache=True)
def unambiguous(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:  # pragma: no cover
    """The admissible pairs of ``cost`` and whether no row and no column holds two of them (then they are the optimal
    assignment)."""
    rows, cols = np.empty(cost.shape[0], np.intp), np.empty(cost.shape[0], np.intp)
    taken = np.zeros(cost.shape[1], np.bool_)
    n = 0
    for a in range(cost.shape[0]):
        col = -1
        for b in range(cost.shape[1]):
            if cost[a, b] < 0.0:
                if col >= 0 or taken[b]:
                    return rows[:0], cols[:0], False
                col = b
        if col >= 0:
            taken[col] = True
            rows[n], cols[n] = a, col
            n += 1
    return rows[:n], cols[:n], True


def assign(pred: np.ndarray, gate: np.ndarray | float, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Optimal one-to-one matching of tracks to points, each pair inside the track's gate (see ``gated_cost``)."""
    if len(pred) == 0 or len(points) == 0:
        return np.empty(0, np.intp), np.empty(0, np.intp)
    return match(gated_cost(pred, gate, points))


def rigid_signature(points: np.ndarray, partners: np.ndarray, mean: np.ndarray, sd: np.ndarray,
               tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How far points ``(B, 3)`` break each marker's distances to its rigid partners, how many partners count, and
    how many of those distances are broken.

    ``partners`` are the partners' positions, ``(P, 3)`` for all points or ``(B, P, 3)`` one set per point, NaN where
    unseen; ``mean``, ``sd`` ``(A, P)`` the learnt distances of each of A markers to each partner, NaN where a partner
    is not rigid with it. Returns ``(A, B)`` worst distance errors in units of ``tolerance + 3 sd`` (0 without
    partners), ``(A, B)`` partner counts and ``(A, B)`` counts of errors above 1. Two partners hold a point to a
    circle, three to a point: this recognises a marker whose rigid body has too few markers left to fit a pose (a
    two-marker remnant), and one partner is enough to rule a point out.
    """
    if partners.ndim == 2:
        partners = np.repeat(partners[None], len(points), axis=0)
    # one layout of every array, so that one compiled form serves every caller (``mocap.compiled`` makes it)
    c = np.ascontiguousarray
    return rigid_signature_compiled(c(points, dtype=np.float64), c(partners, dtype=np.float64),
                                    c(mean, dtype=np.float64),
                      c(sd, dtype=np.float64), float(tolerance))


@njit(cache=True)
def rigid_signature_compiled(points: np.ndarray, partners: np.ndarray, mean: np.ndarray, sd: np.ndarray,
                             tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """``rigid_signature`` with one set of partners ``(B, P, 3)`` per point, for compiled callers: the labeller
    asks for it several times a frame."""
    broken = np.zeros((mean.shape[0], len(points)))
    count = np.zeros((mean.shape[0], len(points)), np.int64)
    violated = np.zeros((mean.shape[0], len(points)), np.int64)
    for b in range(len(points)):
        for p in range(mean.shape[1]):
            d = distance(points[b], partners[b, p])
            for a in range(mean.shape[0]):
                error = abs(d - mean[a, p]) / (tolerance + 3.0 * sd[a, p])
                if np.isfinite(error):  # NaN: the partner is not seen, or not rigid with that marker
                    count[a, b] += 1
                    broken[a, b] = max(broken[a, b], error)
                    violated[a, b] += error > 1.0
    return broken, count, violated


def screened(cost: np.ndarray, broken: np.ndarray, partners: np.ndarray, violated: np.ndarray) -> np.ndarray:
    """Gated costs (``gated_cost``) of points screened by their ``rigid_signature``: a point cannot be the marker
    when it breaks the distance to a rigid partner by ``VETO`` tolerances or those to all its partners, and it must
    lie within half the gate when it breaks some of them."""
    cost = np.where(broken > 1.0, np.minimum(2.0 * cost + 1.0, 0.0), cost)
    return np.where((broken > VETO) | ((violated >= 1) & (violated == partners)), 0.0, cost)

