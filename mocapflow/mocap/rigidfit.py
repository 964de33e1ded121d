"""Rigid fits: the rotation and translation that best map one set of points onto another (Aristidou 2008, 4.3).

One module for every way the project fits a rigid body, all the same least-squares rotation as scipy's
``Rotation.align_vectors`` (Kabsch):

- ``rotor``: from the eigenvector of Horn's 4x4 quaternion matrix (Aristidou 4.3, Horn 1987), for thousands of
  frames in one batched ``eigh`` call; ``fit_pose`` builds on it: a segment's pose ``world = R @ local + t`` in every
  frame from whichever of its markers are visible, either free (centroid alignment) or pivoting about a known point
  such as the joint with its parent.
- ``kabsch`` / ``RigidFit``: a batched SVD for many point sets at once, ``RigidFit`` keeping what depends on the
  local points alone for a caller fitting the same sets to many frames.
- ``fit_one``: the same for a single point set, with less overhead (one frame's segment in the occlusion filler).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.linalg.lapack import dgesdd
from scipy.spatial.transform import Rotation, Slerp


def rotor(reference: np.ndarray, observed: np.ndarray,
          weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rotations ``q`` with ``observed ≈ q.apply(reference)`` in the weighted least-squares sense, per frame.

    ``reference`` and ``observed`` are (..., n, 3) vectors, already relative to the rotation centre (the caller
    subtracts centroids or a pivot); NaN rows and zero ``weights`` are ignored. Returns scalar-last quaternions
    (..., 4) and the relative gap between the two largest eigenvalues of Horn's matrix N, in [0, 1]: near 0 the
    rotation is not determined (fewer than two non-parallel vectors, e.g. two markers about their common line).
    """
    x = np.asarray(reference, dtype=np.float64)
    y = np.asarray(observed, dtype=np.float64)
    if x.shape != y.shape:
        x, y = np.broadcast_arrays(x, y)
    both = np.isfinite(x).all(-1) & np.isfinite(y).all(-1)
    w = np.asarray(both * (1.0 if weights is None else np.asarray(weights, dtype=np.float64)))
    x = np.where(w[..., None] > 0, x, 0.0)
    y = np.where(w[..., None] > 0, y, 0.0)
    s = np.einsum("...n,...na,...nb->...ab", w, x, y)  # S_ab = sum x_a y_b (Schoenauer 3.7.4)
    n = (s.reshape(*s.shape[:-2], 9) @ _HORN).reshape(*s.shape[:-2], 4, 4)
    values, vectors = np.linalg.eigh(n)
    q = vectors[..., :, 3]  # Horn's (w, x, y, z) for the largest eigenvalue
    scale = np.abs(values).max(-1)
    gap = (values[..., 3] - values[..., 2]) / np.maximum(scale, 1e-300)  # 0 where N is 0
    return np.concatenate([q[..., 1:], q[..., :1]], -1), gap


def _horn_map() -> np.ndarray:
    """(9, 16): Horn's symmetric 4x4 matrix N as a linear map of S = sum x y^T (row-major), N = S.ravel() @ map.

    Diagonal: sxx + syy + szz, sxx - syy - szz, -sxx + syy - szz, -sxx - syy + szz; off it, symmetric: syz - szy,
    szx - sxz, sxy - syx (row 0), sxy + syx, szx + sxz (row 1), syz + szy (row 2)."""
    terms = {(0, 0): "+xx +yy +zz", (1, 1): "+xx -yy -zz", (2, 2): "-xx +yy -zz", (3, 3): "-xx -yy +zz",
             (0, 1): "+yz -zy", (0, 2): "+zx -xz", (0, 3): "+xy -yx", (1, 2): "+xy +yx", (1, 3): "+zx +xz",
             (2, 3): "+yz +zy"}
    out = np.zeros((9, 16))
    for (i, j), sums in terms.items():
        for term in sums.split():
            source = 3 * "xyz".index(term[1]) + "xyz".index(term[2])
            out[source, [4 * i + j, 4 * j + i]] = 1.0 if term[0] == "+" else -1.0
    return out


_HORN = _horn_map()


def kabsch(local: np.ndarray, world: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted least-squares rigid transforms ``world ~ R @ local + t`` for a batch of point sets.

    ``local``/``world`` (B, M, 3) finite, ``weight`` (B, M) with zero for absent points. A batched SVD: this runs
    every frame, where scipy's ``Rotation.align_vectors`` would take one set per call and ``rotor`` (Horn's
    eigenvector, plus the quaternion-to-matrix step) costs about twice as much. Returns R (B, 3, 3), t (B, 3) and
    ``ok`` (B,): False where the points do not fix a rotation (fewer than three, or collinear).
    """
    return RigidFit(local, weight)(world)


class RigidFit:
    """``kabsch`` with its local points and weights fixed: what depends on them alone is worked out once, for a
    caller fitting the same point sets to many frames."""

    def __init__(self, local: np.ndarray, weight: np.ndarray) -> None:
        w = weight / np.maximum(weight.sum(axis=1), 1e-300)[:, None]
        self.rows = w[:, None]  # (B, 1, M): weighted means as products
        self.columns = w[..., None]  # (B, M, 1)
        self.centre = (self.rows @ local)[:, 0]
        self.centred = (local - self.centre[:, None]).transpose(0, 2, 1)  # (B, 3, M)
        self.enough = (weight > 0).sum(axis=1) >= 3

    def __call__(self, world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """R, t and ``ok`` of ``kabsch`` for the world points (B, M, 3)."""
        cw = (self.rows @ world)[:, 0]
        h = self.centred @ ((world - cw[:, None]) * self.columns)
        u, s, vt = np.linalg.svd(h)
        r = vt.transpose(0, 2, 1) @ u.transpose(0, 2, 1)  # V U^T, a reflection where its determinant is negative
        flip = 2.0 * (np.linalg.det(r) < 0)  # there V diag(1, 1, -1) U^T, without indexing the batch
        r -= flip[:, None, None] * (vt[:, 2, :, None] * u[:, None, :, 2])
        t = cw - (r @ self.centre[..., None])[..., 0]
        return r, t, self.enough & (s[:, 1] > 1e-6 * s[:, 0])


def fit_one(local: np.ndarray, world: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``kabsch`` for a single point set (M, 3) with less overhead (LAPACK's SVD called directly, without numpy's
    wrapper); None where the points do not fix a rotation."""
    w = weight / weight.sum()
    cl, cw = w @ local, w @ world
    u, s, vt, info = dgesdd((local - cl).T @ ((world - cw) * w[:, None]))
    if info or s[1] <= 1e-6 * s[0]:
        return None
    r = vt.T @ u.T
    a, b, c, d, e, f, g, h, i = r.ravel().tolist()
    if a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) < 0:  # a reflection: flip the last axis
        r -= 2 * np.outer(vt[2], u[:, 2])
    return r, cw - r @ cl




@dataclass
class PoseFit:
    """Per-frame poses of one segment: ``world = R @ local + t``; NaN where too few markers were visible."""

    rotations: np.ndarray  # (F, 4) scalar-last quaternions
    translations: np.ndarray  # (F, 3) mm
    determined: np.ndarray  # (F,) bool: the data fixed all three rotation angles
    rotation_matrices: np.ndarray  # (F, 3, 3) the rotations as matrices, NaN where the pose is unknown
    local: np.ndarray  # (n, 3) the markers in the segment frame
    observed: np.ndarray  # (F, n, 3) the markers fitted, NaN where unseen

    @cached_property
    def residual(self) -> np.ndarray:
        """(F,) RMS distance between fitted and observed markers, mm; NaN where the pose is unknown. Worked out on
        first use: a caller that only poses (the skeleton, frame after frame) does not pay for it."""
        fitted = np.einsum("f...ab,...nb->f...na", self.rotation_matrices, self.local) + self.translations[..., None, :]
        seen = np.isfinite(self.observed).all(-1)
        err = np.where(seen, ((fitted - self.observed) ** 2).sum(-1), 0.0).sum(-1)
        known = np.isfinite(self.rotations).all(-1)
        return np.where(known, np.sqrt(err / np.maximum(seen.sum(-1), 1)), np.nan)

    def subset(self, frames: np.ndarray) -> PoseFit:
        """The poses of some frames only."""
        return PoseFit(self.rotations[frames], self.translations[frames], self.determined[frames],
                       self.rotation_matrices[frames], self.local, self.observed[frames])


def quaternion_matrices(quaternions: np.ndarray) -> np.ndarray:
    """(..., 3, 3) matrices of scalar-last quaternions, NaN rows giving NaN matrices (scipy rejects NaN).

    The arithmetic of scipy's ``Rotation.from_quat(q).as_matrix()`` (normalise, then the products below), operation
    for operation, so the matrices are bit for bit scipy's, without building a ``Rotation`` on every call."""
    q = np.asarray(quaternions, dtype=np.float64)
    norm = np.sqrt(((q[..., 0] * q[..., 0] + q[..., 1] * q[..., 1]) + q[..., 2] * q[..., 2]) + q[..., 3] * q[..., 3])
    if (norm == 0).any():
        raise ValueError("Found zero norm quaternions in `quat`.")
    u = q / norm[..., None]
    p = (u[..., :, None] * u[..., None, :]).reshape(*q.shape[:-1], 16)  # p[4 i + j] = u_i u_j, (x, y, z, w)
    out = np.empty((*q.shape[:-1], 9))
    # diagonal: x2 - y2 - z2 + w2, -x2 + y2 - z2 + w2, -x2 - y2 + z2 + w2; the signs only flip exactly
    out[..., _DIAGONAL] = ((p[..., _SQUARES[0]] * _FIRST + p[..., _SQUARES[1]] * _SECOND)
                           + p[..., _SQUARES[2]] * _THIRD) + p[..., _SQUARES[3]]
    # off the diagonal: 2 (xy - zw), 2 (xz + yw), 2 (xy + zw), 2 (yz - xw), 2 (xz - yw), 2 (yz + xw)
    out[..., _OFF] = 2 * (p[..., _PRODUCTS[0]] + p[..., _PRODUCTS[1]] * _SIGNS)
    return out.reshape(*q.shape[:-1], 3, 3)


_DIAGONAL, _OFF = np.array([0, 4, 8]), np.array([1, 2, 3, 5, 6, 7])
_SQUARES = np.array([[0, 0, 0], [5, 5, 5], [10, 10, 10], [15, 15, 15]])
_PRODUCTS = np.array([[1, 2, 1, 6, 2, 6], [11, 7, 11, 3, 7, 3]])
_FIRST, _SECOND, _THIRD = np.array([1.0, -1.0, -1.0]), np.array([-1.0, 1.0, -1.0]), np.array([-1.0, -1.0, 1.0])
_SIGNS = np.array([-1.0, 1.0, 1.0, -1.0, -1.0, 1.0])


def fit_pose(local: np.ndarray, observed: np.ndarray, pivot_local: np.ndarray | None = None,
             pivot_world: np.ndarray | None = None, *, hold: bool = False, min_gap: float = 1e-3) -> PoseFit:
    """Pose of a rigid marker set in every frame, from the visible markers only.

    ``local`` (n, 3) are the markers in the segment frame, ``observed`` (F, n, 3) their positions with NaN gaps.
    Free fit (Horn): align the centroids of the markers visible in that frame, so a missing marker moves neither
    centroid. With a pivot (``pivot_local`` (3,), ``pivot_world`` (F, 3)), the segment only rotates about that point,
    which stays exactly where it is (Schoenauer 3.8.2): one marker and the pivot then give a pose, and frames whose
    pivot is NaN fall back to the free fit. Frames whose rotation the points do not fix (eigenvalue gap below
    ``min_gap``: one direction only) are flagged in ``determined``; with ``hold`` their rotation becomes the smallest
    turn of the previous frame's (before a first determined frame: the next one's) that matches the visible
    direction, so a segment seen through two points keeps turning plausibly instead of spinning about them.

    Several segments are fitted in one call by giving them a batch axis after the frames: ``local`` (S, n, 3),
    ``observed`` (F, S, n, 3), pivots (S, 3) and (F, S, 3), each segment's markers padded to a common n with rows
    that are never seen (any finite ``local``, NaN ``observed``); every result then has that axis too, and each
    segment's numbers are exactly those of fitting it alone.
    """
    local = np.asarray(local, dtype=np.float64)
    obs = np.asarray(observed, dtype=np.float64)
    seen = np.asarray(np.isfinite(obs).all(-1))
    count = seen.sum(-1)
    share = (seen / np.maximum(count, 1)[..., None])[..., None, :]  # (F, ..., 1, n): centroids as products
    origin_loc = (share @ local)[..., 0, :]
    origin_obs = (share @ np.where(seen[..., None], obs, 0.0))[..., 0, :]
    free: np.ndarray | bool = True
    if pivot_local is not None and pivot_world is not None:
        pivot_world = np.asarray(pivot_world, dtype=np.float64)
        pinned = np.isfinite(pivot_world).all(-1)
        free = ~pinned
        origin_loc = np.where(pinned[..., None], np.asarray(pivot_local, dtype=np.float64), origin_loc)
        origin_obs = np.where(pinned[..., None], pivot_world, origin_obs)
    quats, gap = rotor(local[None] - origin_loc[..., None, :], obs - origin_obs[..., None, :])
    usable = np.where(free, count >= 2, count >= 1)
    quats[~usable] = np.nan
    determined = usable & (gap >= min_gap)
    if hold and local.ndim == 2:
        _hold(quats, determined, local, obs, origin_loc, origin_obs)
    elif hold:  # only segments with a frame to hold and one to hold it from
        todo = (np.isfinite(quats).all(-1) & ~determined).any(0) & determined.any(0)
        for s in np.flatnonzero(todo):
            _hold(quats[:, s], determined[:, s], local[s], obs[:, s], origin_loc[:, s], origin_obs[:, s])
    matrices = quaternion_matrices(quats)
    t = origin_obs - np.einsum("f...ab,f...b->f...a", matrices, origin_loc)
    return PoseFit(quats, t, determined, matrices, local, obs)


def _hold(quats: np.ndarray, determined: np.ndarray, local: np.ndarray, observed: np.ndarray,
          origin_loc: np.ndarray, origin_obs: np.ndarray) -> None:
    """In place: undetermined frames take the smallest turn that points their longest visible vector (from the
    origin) at the data, from the rotation interpolated (slerp) between the nearest determined frames before and
    after (or the nearest one, at an end)."""
    todo = np.flatnonzero(np.isfinite(quats).all(1) & ~determined)
    known = np.flatnonzero(determined)
    if not len(known):
        return
    after = np.searchsorted(known, todo)
    for f, k in zip(todo, after, strict=True):
        if 0 < k < len(known):
            a, b = known[k - 1], known[k]
            pair = Rotation.from_quat(quats[[a, b]])
            prior = Slerp([a, b], pair)([f])[0]
        else:
            prior = Rotation.from_quat(quats[known[min(k, len(known) - 1)]])
        seen = np.isfinite(observed[f]).all(1)
        u, w = local[seen] - origin_loc[f], observed[f, seen] - origin_obs[f]
        longest = int(np.argmax(np.linalg.norm(u, axis=1)))
        turn, _ = Rotation.align_vectors(w[longest][None], prior.apply(u[longest])[None])
        quats[f] = (turn * prior).as_quat()

