"""Reference gap-filling methods of the literature, each written from its paper, for the benchmarks: interpolation,
Gløersen & Federolf's PCA reconstruction (PLoS ONE 2016; mocapflow's offline fill uses it, with each gap made to meet
the observed trajectory, in ``mocapflow.mocap.filling.posture``) and Burke & Lasenby's low-dimensional Kalman smoother
(J Biomech 2016). Every method takes (F, N, 3) positions with NaN gaps and returns
them filled (NaN only where it cannot fill).

Both PCA methods work on the world coordinates, whose variance the subject's travel dominates: they keep the
components explaining 99.99 % of it (99 % keeps little more than the travel; measured on the CMU files, 99 % gives
three times the error of 99.99 %)."""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline

from mocapflow.mocap.filling.posture import interpolate_linear, posture_fill, training_frames


def interpolate(x: np.ndarray, kind: str) -> np.ndarray:
    """Linear or cubic-spline interpolation of every marker over its gaps; a gap at an end holds the nearest seen
    position (neither extrapolates sensibly)."""
    if kind == "linear":
        return interpolate_linear(x)
    out = x.copy()
    frames = np.arange(len(x))
    for m in range(x.shape[1]):
        known = np.isfinite(x[:, m]).all(axis=1)
        if known.all() or known.sum() < 2:
            continue
        f = frames[known]
        inside = (frames > f[0]) & (frames < f[-1]) & ~known
        out[inside, m] = CubicSpline(f, x[known, m])(frames[inside])
        out[frames < f[0], m] = x[f[0], m]
        out[frames > f[-1], m] = x[f[-1], m]
    return out


def pca_fill(x: np.ndarray, variance: float = 0.9999) -> np.ndarray:
    """Gløersen & Federolf (2016), as the paper has it (mocapflow's ``posture_fill`` without meeting the ends): the
    marker coordinates, weighted by each marker's distance to the markers with gaps, decomposed into principal
    components learnt from the complete frames; in every frame with gaps, the scores of the components explaining
    ``variance`` of the variance fitted to the visible coordinates and the missing coordinates read from them."""
    return posture_fill(x, variance, meet_ends=False)


def kalman_smoother_fill(x: np.ndarray, rate: float, variance: float = 0.9999) -> np.ndarray:
    """Burke & Lasenby (2016): the body's motion as the scores of a few principal components (those explaining
    ``variance``, learnt from the complete frames), followed through the recording by a Kalman filter with a
    constant-velocity model in that low-dimensional space, whose measurement in each frame is the visible marker
    coordinates, then smoothed backwards (Rauch-Tung-Striebel); the missing coordinates are read from the smoothed
    scores. Process noise per component from the second differences of its scores, measurement noise from the
    variance the discarded components leave."""
    flat = x.reshape(len(x), -1)
    missing = ~np.isfinite(flat)
    if not missing.any():
        return x.copy()
    frames, dims = flat.shape
    train = training_frames(flat, variance)
    mean = train.mean(axis=0)
    _, s, vt = np.linalg.svd(train - mean, full_matrices=False)
    d = int(np.searchsorted(np.cumsum(s**2) / (s**2).sum(), variance)) + 1
    basis = vt[:d].T  # (dims, d)
    noise = max(float((s[d:] ** 2).sum() / len(train) / dims), 1.0)  # mm^2 per coordinate
    scores = (train - mean) @ basis
    dt = 1.0 / rate
    q = 1.5 * np.var(np.diff(scores, 2, axis=0), axis=0) / dt**3 if len(scores) > 3 else np.ones(d)
    transition = np.block([[np.eye(d), dt * np.eye(d)], [np.zeros((d, d)), np.eye(d)]])
    process = np.block([[np.diag(q) * dt**3 / 3, np.diag(q) * dt**2 / 2], [np.diag(q) * dt**2 / 2, np.diag(q) * dt]])
    state = np.zeros(2 * d)
    cov = np.block([[np.diag(s[:d] ** 2 / len(train)), np.zeros((d, d))], [np.zeros((d, d)), np.diag(q)]])
    states, covs, priors, prior_covs = (np.zeros((frames, 2 * d)), np.zeros((frames, 2 * d, 2 * d)),
                                        np.zeros((frames, 2 * d)), np.zeros((frames, 2 * d, 2 * d)))
    for f in range(frames):
        if f:
            state, cov = transition @ state, transition @ cov @ transition.T + process
        priors[f], prior_covs[f] = state, cov
        seen = ~missing[f]
        h = basis[seen]  # the measured coordinates depend on the scores only
        info = np.linalg.inv(cov)
        info[:d, :d] += h.T @ h / noise
        cov = np.linalg.inv(info)
        cov = (cov + cov.T) / 2
        gain_rhs = np.zeros(2 * d)
        gain_rhs[:d] = h.T @ (flat[f, seen] - mean[seen] - h @ state[:d]) / noise
        state = state + cov @ gain_rhs
        states[f], covs[f] = state, cov
    for f in range(frames - 2, -1, -1):  # Rauch-Tung-Striebel
        gain = covs[f] @ transition.T @ np.linalg.inv(prior_covs[f + 1])
        states[f] = states[f] + gain @ (states[f + 1] - priors[f + 1])
        covs[f] = covs[f] + gain @ (covs[f + 1] - prior_covs[f + 1]) @ gain.T
    out = np.where(missing, mean + states[:, :d] @ basis.T, flat)
    return out.reshape(x.shape)
