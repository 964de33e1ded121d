"""Where a lost marker is now, from snapshots of it with its neighbours (the thesis's local *Marker Set* distance)."""

from __future__ import annotations

import numpy as np

from mocapflow.mocap.labelling.assignment import nanmedian, norm
from mocapflow.mocap.labelling.config import CANDIDATES
from mocapflow.mocap.rigidfit import kabsch


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
    others).
    """
    n = len(poses)
    common = np.isfinite(now[:, None, :, 0]) & np.isfinite(poses[..., 1:, 0]) & (trust[:, None] > 0)
    usable = (common.sum(axis=2) >= 3) & np.isfinite(poses[..., 0, 0])
    now_d = norm(now[:, :, None] - now[:, None])
    then_d = norm(poses[..., 1:, None, :] - poses[..., None, 1:, :])
    pair = common[..., :, None] & common[..., None, :]
    change = np.where(pair, np.abs(then_d - now_d[:, None]), 0.0).sum(axis=(2, 3))
    change = np.where(usable, change / np.maximum(pair.sum(axis=(2, 3)), 1), np.inf)
    order = np.argsort(change, axis=1)[:, :CANDIDATES]
    bi, ci = np.nonzero(np.isfinite(np.take_along_axis(change, order, axis=1)))
    si = order[bi, ci]
    place = np.full((n, 3), np.nan)
    misfit = np.full(n, np.nan)
    spread = np.full(n, np.nan)
    if len(bi) == 0:
        return place, misfit, spread
    pose, target = poses[bi, si], now[bi]
    w = np.where(common[bi, si], trust[bi], 0.0)
    shift = np.abs(then_d[bi, si] - now_d[bi])
    shift = np.where((w[:, :, None] > 0) & (w[:, None, :] > 0), shift, np.nan)
    shift[:, np.arange(shift.shape[1]), np.arange(shift.shape[1])] = np.nan
    moved_by = nanmedian(shift)
    typical = nanmedian(moved_by)[:, None]
    out = (moved_by > np.maximum(3.0 * typical, tolerance)) & ((w > 0).sum(axis=1) >= 4)[:, None]
    w = np.where(((w > 0) & ~out).sum(axis=1, keepdims=True) >= 3, np.where(out, 0.0, w), w)
    use = (w > 0)[..., None]  # absent points may hold NaN
    r, t, _ = kabsch(np.where(use, pose[:, 1:], 0.0), np.where(use, target, 0.0), w)
    moved = np.einsum("bij,bnj->bni", r, pose) + t[:, None]
    sq = np.where(w > 0, ((moved[:, 1:] - target) ** 2).sum(axis=2), 0.0)
    fit = np.sqrt((w * sq).sum(axis=1) / w.sum(axis=1))
    # the best of each marker's candidates
    rank = np.full((n, CANDIDATES), np.inf)
    rank[bi, ci] = fit
    pick = np.full((n, CANDIDATES), -1)
    pick[bi, ci] = np.arange(len(bi))
    chosen = pick[np.arange(n), rank.argmin(axis=1)]
    found = chosen >= 0
    c = chosen[found]
    place[found] = moved[c, 0]
    misfit[found] = fit[c]
    at = np.full((n, CANDIDATES, 3), np.nan)
    at[bi, ci] = moved[:, 0]
    spread[found] = np.nanmax(norm(at[found] - place[found, None]), axis=1)
    return place, misfit, spread

