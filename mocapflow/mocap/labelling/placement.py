"""Where a lost marker is now, from snapshots of it with its neighbours (the thesis's local *Marker Set* distance)."""

from __future__ import annotations

import numpy as np
from numba import njit

from mocapflow.mocap.labelling.assignment import distance
from mocapflow.mocap.labelling.config import CANDIDATES
from mocapflow.mocap.rigidfit import kabsch_into, place


def place_marker(poses: np.ndarray, now: np.ndarray, trust: np.ndarray,
                 tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where a marker is now, from snapshots of it with its neighbours and the neighbours' current positions.

    ``poses`` ``(B, S, 1 + K, 3)``: S snapshots, row 0 the marker; ``now`` ``(B, K, 3)``, NaN where unseen; ``trust``
    ``(B, K)`` weights of the neighbours. The snapshots whose neighbour distances are closest to the current ones (3
    or more neighbours in common) are fitted rigidly to the neighbours, and the best fit places the marker: the
    minimum over poses of Kirk et al.'s *Marker Set* distance, on the thesis's local neighbourhood. Comparing
    distances first, which needs no fit, keeps the cost at ``CANDIDATES`` fits per marker; fitting more than one
    rejects a mirror-image pose, which has the same distances. A neighbour whose distances to the others changed far
    more than theirs (the median change of its distances above three times the typical one, and above
    ``tolerance``) has moved relative to them and is left out, as long as three remain. Returns ``(B, 3)`` positions,
    ``(B,)`` weighted RMS misfits (NaN where no snapshot fits) and ``(B,)`` spreads: how far apart the candidates
    place the marker, which is large when the neighbours leave a turn undetermined (two rigid partners and loose
    others). Compiled, marker by marker: a frame that must place several lost markers pays tens of microseconds, not
    a millisecond.
    """
    where, misfit, spread = np.full((len(poses), 3), np.nan), np.full(len(poses), np.nan), np.full(len(poses), np.nan)
    _place(np.ascontiguousarray(poses, dtype=np.float64), np.ascontiguousarray(now, dtype=np.float64),
           np.ascontiguousarray(trust, dtype=np.float64), float(tolerance), CANDIDATES, where, misfit, spread)
    return where, misfit, spread


@njit(cache=True)
def _place(poses: np.ndarray, now: np.ndarray, trust: np.ndarray, tolerance: float, candidates: int,
           where: np.ndarray, misfit: np.ndarray, spread: np.ndarray) -> None:  # pragma: no cover
    """``place_marker`` into ``where``, ``misfit`` and ``spread`` (NaN where no snapshot fits)."""
    snapshots, k = poses.shape[1], now.shape[1]
    common = np.empty((snapshots, k), np.bool_)
    change = np.empty(snapshots)
    now_d = np.empty((k, k))
    shift, moved_by, row = np.empty((k, k)), np.empty(k), np.empty(k)
    w = np.empty(k)
    r, t, at = np.empty((3, 3)), np.empty(3), np.empty(3)
    moved = np.empty((candidates, 3))
    fits = np.full(candidates, np.inf)
    for b in range(len(poses)):
        for i in range(k):
            for j in range(k):
                now_d[i, j] = distance(now[b, i], now[b, j])
        for s in range(snapshots):
            seen = 0
            for i in range(k):
                common[s, i] = np.isfinite(now[b, i, 0]) and np.isfinite(poses[b, s, 1 + i, 0]) and trust[b, i] > 0
                seen += common[s, i]
            change[s] = np.inf
            if seen < 3 or not np.isfinite(poses[b, s, 0, 0]):
                continue
            total, pairs = 0.0, 0
            for i in range(k):
                for j in range(k):
                    if common[s, i] and common[s, j]:
                        total += abs(distance(poses[b, s, 1 + i], poses[b, s, 1 + j]) - now_d[i, j])
                        pairs += 1
            change[s] = total / pairs
        order = np.argsort(change, kind="mergesort")[:candidates]
        n_fits = 0
        for c in range(len(order)):
            fits[c] = np.inf
            moved[c] = np.nan
            s = order[c]
            if not np.isfinite(change[s]):
                continue
            n_fits += 1
            used, total_w = 0, 0.0
            for i in range(k):
                w[i] = trust[b, i] if common[s, i] else 0.0
                used += w[i] > 0
            # a neighbour whose distances to the others changed far more than theirs has moved: left out
            for i in range(k):
                for j in range(k):
                    shift[i, j] = np.nan
                    if i != j and w[i] > 0 and w[j] > 0:
                        then = distance(poses[b, s, 1 + i], poses[b, s, 1 + j])
                        shift[i, j] = abs(then - now_d[i, j])
                moved_by[i] = _nanmedian(shift[i], row)
            typical = _nanmedian(moved_by, row)
            limit = np.nan if np.isnan(typical) else max(3.0 * typical, tolerance)
            kept = 0
            for i in range(k):
                kept += w[i] > 0 and not (used >= 4 and moved_by[i] > limit)
            if kept >= 3:
                for i in range(k):
                    if used >= 4 and moved_by[i] > limit:
                        w[i] = 0.0
            for i in range(k):
                total_w += w[i]
            kabsch_into(poses[b, s, 1:], now[b], w / max(total_w, 1e-300), r, t)
            sq = 0.0
            for i in range(k):
                if w[i] > 0:
                    place(r, poses[b, s, 1 + i], t, at)
                    square = 0.0
                    for a in range(3):
                        square += (at[a] - now[b, i, a]) ** 2
                    sq += w[i] * square
            fits[c] = np.sqrt(sq / total_w)
            place(r, poses[b, s, 0], t, moved[c])
        if n_fits == 0:
            continue
        best = -1  # the best fit (a NaN fit, from points that fix no rotation, first, as numpy's argmin would)
        for c in range(len(order)):
            if np.isnan(fits[c]):
                best = c
                break
            if best < 0 or fits[c] < fits[best]:
                best = c
        where[b] = moved[best]
        misfit[b] = fits[best]
        far = np.nan
        for c in range(len(order)):
            gap = distance(moved[c], moved[best])
            if np.isfinite(gap) and not gap <= far:
                far = gap
        spread[b] = far


@njit(cache=True)
def _nanmedian(values: np.ndarray, space: np.ndarray) -> float:  # pragma: no cover
    """The median of the finite ``values`` (NaN when none), sorting them in ``space``."""
    n = 0
    for v in values:
        if np.isfinite(v):
            space[n] = v
            n += 1
    if n == 0:
        return np.nan
    ordered = np.sort(space[:n])
    return (ordered[(n - 1) // 2] + ordered[n // 2]) / 2
