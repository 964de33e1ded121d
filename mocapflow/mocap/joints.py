"""Joint positions and skeleton topology (Schoenauer 2007, 3.5 and 3.7.7).

A joint between segments a and b sits where its distance to every marker of both segments stays constant over
time. ``fit_joint_variance`` places the joint in every frame so as to minimise the joint cost

    jc(a, b) = 1 / |a ∪ b| * sum_n [ var_f |c_f - m_n,f| + alpha * mean_f |c_f - m_n,f| ]

(3.5.1): the per-frame centres ``c_f`` are the unknowns, the alpha term keeps the joint from drifting to infinity,
where every variance also vanishes. The minimisation (see ``fit_joint_variance``) starts from the closed-form centre
of rotation (``cor.SequentialCoR``) or, for segments whose orientation the markers do not fix, from the centroid of
both segments' markers (Schoenauer's start).

The topology is the minimum spanning tree of the joint costs of every segment pair (3.7.7); its root is the segment
with the most joints, ties broken by the smallest summed path length to the other segments (the most central).

A hinge (knee, elbow) leaves a whole axis of centres that fit equally well. ``place_on_axis`` then picks one point:
by default the axis point level with the neighbouring joints (a knee lies in the plane of the hip and ankle centres
that is perpendicular to its axis); when the two segments have no other joint, the mid-plane between the segments'
marker centroids.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree, shortest_path

ALPHA = 1e-3
"""Weight (mm^2 per mm) of the mean marker distance in the joint cost: enough to rule out a joint at infinity, small
enough to move a well-determined joint by well under a millimetre."""


@dataclass
class JointTrack:
    """A joint estimated frame by frame, with the statistics of its distances to the markers."""

    centres: np.ndarray  # (F, 3) mm, NaN where no marker of either segment was seen
    cost: float  # joint cost jc (mm^2): mean distance variance plus alpha times mean distance
    distance_mean: float  # mean over markers of the mean marker-to-joint distance, mm
    distance_sd: float  # mean over markers of the standard deviation of that distance, mm


def marker_centroid(markers: np.ndarray) -> np.ndarray:
    """(F, 3) centroid of the visible markers per frame, NaN where none is: Schoenauer's start for a joint."""
    seen = np.isfinite(markers).all(-1)
    total = np.where(seen[..., None], markers, 0.0).sum(1)
    count = seen.sum(1)[:, None]
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def distance_stats(centres: np.ndarray, markers: np.ndarray, alpha: float = ALPHA) -> tuple[float, float, float]:
    """Joint cost, mean distance and mean distance SD of per-frame centres (F, 3) to markers (F, M, 3)."""
    d = np.linalg.norm(markers - centres[:, None], axis=-1)
    seen = np.isfinite(d)
    count = np.maximum(seen.sum(0), 1)
    mean = np.where(seen, d, 0.0).sum(0) / count
    var = np.where(seen, (d - mean) ** 2, 0.0).sum(0) / count
    used = seen.any(0)
    return (float((var + alpha * mean)[used].mean()), float(mean[used].mean()), float(np.sqrt(var[used]).mean()))


class _RadiiProblem:
    """The joint cost as a function of per-marker radii alone, every frame's centre following by 3.5.2.

    With a radius ``r_n`` per marker as extra unknown, ``sum_f (d_nf - r_n)^2 / |m_n|`` is smallest at the mean
    distance, where it equals the distance variance of 3.5.1. For given radii each frame's centre is found on its
    own (Schoenauer's local optimisation, 3.5.2: damped Gauss-Newton on the (F, 3, 3) normal equations of all frames
    at once), so the outer problem has M unknowns instead of 3F. Its gradient follows from the envelope theorem and
    its Hessian is the Schur complement of the per-frame blocks, which lets scipy's trust-region Newton converge in a
    few steps.
    """

    def __init__(self, markers: np.ndarray, seen: np.ndarray, start: np.ndarray, alpha: float) -> None:
        self.m = np.where(seen[..., None], markers, 0.0)
        count = np.maximum(seen.sum(0), 1)
        self.w = np.where(seen, 1.0 / (count * markers.shape[1]), 0.0)
        self.alpha = alpha
        self.c = start.copy()
        self.radii: np.ndarray | None = None

    def initial_radii(self) -> np.ndarray:
        d = np.sqrt(((self.c[:, None] - self.m) ** 2).sum(-1))
        return (self.w * d).sum(0) / np.maximum(self.w.sum(0), 1e-300)

    def _solve(self, radii: np.ndarray, iterations: int = 10, tol_mm: float = 1e-5) -> None:
        if self.radii is not None and np.array_equal(radii, self.radii):
            return
        for _ in range(iterations):
            diff = self.c[:, None] - self.m
            d = np.maximum(np.sqrt((diff * diff).sum(-1)), 1e-9)
            unit = diff / d[..., None]
            grad = np.einsum("fn,fnk->fk", self.w * (2.0 * (d - radii) + self.alpha), unit)
            hess = self._blocks(d, unit)
            step = np.linalg.solve(hess, -grad[..., None])[..., 0]
            self.c = self.c + step
            if np.abs(step).max() < tol_mm:
                break
        diff = self.c[:, None] - self.m
        self.d = np.maximum(np.sqrt((diff * diff).sum(-1)), 1e-9)
        self.unit = diff / self.d[..., None]
        self.radii = radii.copy()

    def _blocks(self, d: np.ndarray, unit: np.ndarray) -> np.ndarray:
        """Per-frame Gauss-Newton Hessians (F, 3, 3), slightly damped so that no frame is singular."""
        w, a = self.w, self.alpha
        hess = np.einsum("fn,fni,fnj->fij", w * (2.0 - a / d), unit, unit)
        hess += (w * a / d).sum(1)[:, None, None] * np.eye(3)
        return hess + (1e-9 * np.trace(hess, axis1=1, axis2=2) + 1e-12)[:, None, None] * np.eye(3)

    def value(self, radii: np.ndarray) -> float:
        self._solve(radii)
        dev = self.d - radii
        return float((self.w * (dev * dev + self.alpha * self.d)).sum())

    def gradient(self, radii: np.ndarray) -> np.ndarray:
        self._solve(radii)
        return -2.0 * (self.w * (self.d - radii)).sum(0)

    def hessian(self, radii: np.ndarray) -> np.ndarray:
        self._solve(radii)
        coupling = -2.0 * self.w[..., None] * self.unit  # (F, M, 3): d^2 f / dr dc
        solved = np.linalg.solve(self._blocks(self.d, self.unit), coupling.transpose(0, 2, 1))  # (F, 3, M)
        return np.diag(2.0 * self.w.sum(0)) - np.einsum("fnk,fkm->nm", coupling, solved)


def fit_joint_variance(markers: np.ndarray, start: np.ndarray, alpha: float = ALPHA,
                       max_iterations: int = 50) -> JointTrack:
    """Per-frame joint centres between two segments minimising the joint cost (Schoenauer 3.5.1).

    ``markers`` (F, M, 3) are the markers of both segments (NaN gaps), ``start`` (F, 3) the initial centres. The
    cost is minimised over per-marker radii by scipy's exact trust-region Newton method, each frame's centre
    following from the radii (see ``_RadiiProblem``). ``max_iterations`` caps the outer solver; a few iterations are
    enough to rank candidate joints. Frames without any marker or without a start keep NaN.
    """
    markers = np.asarray(markers, dtype=np.float64)
    rows = np.isfinite(markers).all(-1).any(1) & np.isfinite(start).all(1)
    centres = np.full((markers.shape[0], 3), np.nan)
    if rows.sum() < 2:
        return JointTrack(centres, np.inf, np.nan, np.nan)
    problem = _RadiiProblem(markers[rows], np.isfinite(markers[rows]).all(-1),
                            np.asarray(start, dtype=np.float64)[rows], alpha)
    result = minimize(problem.value, problem.initial_radii(), jac=problem.gradient, hess=problem.hessian,
                      method="trust-exact", options={"maxiter": max_iterations, "gtol": 1e-8})
    problem.value(result.x)
    centres[rows] = problem.c
    value, mean, sd = distance_stats(centres[rows], markers[rows], alpha)
    return JointTrack(centres, value, mean, sd)


def spanning_tree(costs: np.ndarray) -> tuple[int, list[tuple[int, int]]]:
    """Root and (parent, child) joints of the minimum spanning tree of a symmetric (S, S) joint-cost matrix.

    Non-finite costs mean "no joint possible"; the graph must still connect. The root has the most joints, ties
    broken by the smallest summed path length (in joints) to every other segment. Edges come parents first.
    """
    n = costs.shape[0]
    if n == 1:
        return 0, []
    finite = np.isfinite(costs)
    # csgraph treats 0 as "no edge": shift every finite cost to be strictly positive, order unchanged
    weights = np.where(finite, costs - np.nanmin(np.where(finite, costs, np.nan)) + 1.0, 0.0)
    np.fill_diagonal(weights, 0.0)
    tree = minimum_spanning_tree(weights)
    adjacency = ((tree + tree.T) > 0).astype(float)
    if adjacency.nnz != 2 * (n - 1):
        raise ValueError("the segments do not form one connected body")
    degree = np.asarray(adjacency.sum(1)).ravel()
    hops = shortest_path(adjacency, unweighted=True).sum(1)
    root = int(min(range(n), key=lambda s: (-degree[s], hops[s], s)))
    order, parents = breadth_first_order(adjacency, root, directed=False)
    return root, [(int(parents[s]), int(s)) for s in order[1:]]


def place_on_axis(parent_offset: np.ndarray, child_offset: np.ndarray, parent_axis: np.ndarray,
                  child_axis: np.ndarray, parent_neighbours: list[np.ndarray],
                  child_neighbours: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Move a hinge's centre along its axis (given in both frames) to the level of the neighbouring joints.

    Neighbours are the other (ball) joints of the parent (in its frame) and of the child (in its frame); their mean
    axial coordinate relative to the current centre is the shift. Without neighbours the centre goes to the
    mid-plane between the two segment origins (the marker centroids), i.e. the minimum-norm point of the axis.
    """
    coords = [float(parent_axis @ (a - parent_offset)) for a in parent_neighbours]
    coords += [float(child_axis @ (b - child_offset)) for b in child_neighbours]
    shift = np.mean(coords) if coords else -(parent_axis @ parent_offset + child_axis @ child_offset) / 2
    return parent_offset + shift * parent_axis, child_offset + shift * child_axis
