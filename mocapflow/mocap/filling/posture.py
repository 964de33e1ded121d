"""The whole body's postures, for filling a file offline: Gløersen & Federolf's weighted PCA reconstruction (PLoS ONE
2016), with each gap's reconstruction shifted to meet the marker's observed trajectory at both of its ends.

The marker coordinates of the frames are decomposed into principal components (those explaining ``variance`` of the
variance; the world coordinates, so the subject's travel is the first). Markers near the ones with gaps weigh more
(w = exp(-d^2 / (2 s^2)), d the distance to the nearest marker with a gap, s the median distance between markers).
In a frame with gaps, the scores are fitted to the visible coordinates (least squares) and the missing ones read from
them. A reconstruction errs mostly by a slow offset; so, unlike the paper, a gap's reconstruction is corrected by its
error where the marker is seen just before and just after the gap (the marker reconstructed there as if it were
hidden), blended linearly across the gap (``meet_ends``).

It uses the frames after a gap: files only. ``fill_both_ways`` takes it for the samples the rigid-body filler could
place with no body constraint, and weighs it against the filler elsewhere.
"""

from __future__ import annotations

import numpy as np

TRAINING_FRAMES = 20  # fewer complete frames than this: the components are learnt from every frame, imputed


def gaps(hidden: np.ndarray) -> list[tuple[int, int]]:
    """The gaps of one marker, ``(start, stop)`` frame ranges, from its (F,) ``hidden`` flags."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], hidden.astype(np.int8), [0]])))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def interpolate_linear(x: np.ndarray) -> np.ndarray:
    """(F, N, 3) every marker's gaps bridged by a straight line; a gap at an end holds the nearest seen position; a
    marker never seen stays NaN."""
    out = x.copy()
    frames = np.arange(len(x))
    for m in range(x.shape[1]):
        known = np.isfinite(x[:, m]).all(axis=1)
        if known.all() or not known.any():
            continue
        for axis in range(3):
            out[~known, m, axis] = np.interp(frames[~known], frames[known], x[known, m, axis])
    return out


def training_frames(flat: np.ndarray, variance: float) -> np.ndarray:
    """The frames the components are learnt from: the complete ones, as the paper does; when fewer than
    ``TRAINING_FRAMES`` are, every frame with its gaps imputed by iterated low-rank reconstruction (straight lines
    first, then 20 rounds of replacing the missing entries by their reconstruction), so the components are not those
    of straight lines."""
    missing = ~np.isfinite(flat)
    complete = ~missing.any(axis=1)
    if complete.sum() >= TRAINING_FRAMES:
        return flat[complete]
    filled = interpolate_linear(flat.reshape(len(flat), -1, 3)).reshape(flat.shape)
    usable = np.isfinite(filled).all(axis=1)
    filled, missing = filled[usable], missing[usable]
    for _ in range(20):
        mean = filled.mean(axis=0)
        u, s, vt = np.linalg.svd(filled - mean, full_matrices=False)
        keep = int(np.searchsorted(np.cumsum(s**2) / (s**2).sum(), variance)) + 1
        filled = np.where(missing, mean + (u[:, :keep] * s[:keep]) @ vt[:keep], filled)
    return filled


class PostureModel:
    """Principal postures learnt from a recording (F, N, 3) with gaps; ``reconstruct`` reads a frame's coordinates
    from the visible ones."""

    def __init__(self, x: np.ndarray, variance: float = 0.9999) -> None:
        n = x.shape[1]
        centre = np.nanmean(x, axis=0)
        gappy = ~np.isfinite(x).all(axis=2).all(axis=0)
        apart = np.linalg.norm(centre[:, None] - centre[None], axis=-1)
        distance = apart[:, gappy].min(axis=1) if gappy.any() else np.zeros(n)
        scale = np.median(apart[np.triu_indices(n, 1)]) if n > 1 else 1.0
        self.weight = np.repeat(np.exp(-(distance**2) / (2 * scale**2)), 3)
        train = training_frames(x.reshape(len(x), -1), variance)
        self.mean = train.mean(axis=0)
        _, s, vt = np.linalg.svd((train - self.mean) * self.weight, full_matrices=False)
        keep = int(np.searchsorted(np.cumsum(s**2) / (s**2).sum(), variance)) + 1
        self.basis = vt[:keep].T / self.weight[:, None]  # back to unweighted coordinates

    def reconstruct(self, row: np.ndarray, seen: np.ndarray) -> np.ndarray:
        """(3N,) every coordinate of a frame, from its coordinates ``row`` where ``seen`` (3N,) is True."""
        w = self.weight[seen]
        scores, *_ = np.linalg.lstsq(self.basis[seen] * w[:, None], (row[seen] - self.mean[seen]) * w, rcond=None)
        return self.mean + self.basis @ scores


def posture_fill(x: np.ndarray, variance: float = 0.9999, meet_ends: bool = True) -> np.ndarray:
    """(F, N, 3) every gap of ``x`` filled from the whole body's postures; without ``meet_ends``, the paper's
    reconstruction as it is. NaN where a frame has no visible marker."""
    flat = x.reshape(len(x), -1)
    missing = ~np.isfinite(flat)
    if not missing.any() or missing.all():
        return x.copy()
    model = PostureModel(x, variance)
    rows = flat.copy()
    for f in np.flatnonzero(missing.any(axis=1) & ~missing.all(axis=1)):
        rows[f, missing[f]] = model.reconstruct(flat[f], ~missing[f])[missing[f]]
    out = rows.reshape(x.shape)
    if meet_ends:
        _meet_ends(x, out, model)
    return out


def _meet_ends(x: np.ndarray, out: np.ndarray, model: PostureModel) -> None:
    """Shift each gap's reconstruction in ``out`` by the reconstruction's error where the marker is seen on either
    side of the gap, blended linearly across it (one side's alone for a gap at an end of the recording)."""
    flat = x.reshape(len(x), -1)
    seen_all = np.isfinite(flat)
    hidden = ~np.isfinite(x).all(axis=-1)
    frames = len(x)
    for m in range(x.shape[1]):
        for start, stop in gaps(hidden[:, m]):
            errors: list[np.ndarray | None] = []
            for f in (start - 1, stop):
                if 0 <= f < frames:
                    seen = seen_all[f].copy()
                    seen[3 * m:3 * m + 3] = False
                    errors.append(x[f, m] - model.reconstruct(flat[f], seen)[3 * m:3 * m + 3] if seen.any() else None)
                else:
                    errors.append(None)
            known = [e for e in errors if e is not None]
            if not known:
                continue
            before = known[0] if errors[0] is None else errors[0]
            after = known[-1] if errors[1] is None else errors[1]
            t = (np.arange(start, stop) - start + 1)[:, None] / (stop - start + 1)
            out[start:stop, m] += (1 - t) * before + t * after
