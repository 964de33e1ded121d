"""Rigid-body rotations and centres of rotation between two segments (Aristidou 2008, sections 4.3 and 4.4).

Building blocks shared by calibration, the skeleton solver and joint tracking through occlusions:

- ``rotor``: the rotation that best maps one set of vectors onto another, from the eigenvector of Horn's 4x4
  quaternion matrix (Aristidou 4.3, Horn 1987). It is the same least-squares rotation as scipy's
  ``Rotation.align_vectors`` (Kabsch), computed for thousands of frames in one batched ``eigh`` call.
- ``fit_pose``: a segment's pose ``world = R @ local + t`` in every frame from whichever of its markers are visible,
  either free (centroid alignment) or pivoting about a known point such as the joint with its parent.
- ``SequentialCoR``: the closed-form centre of rotation of Aristidou 4.4, the point fixed in both segments' frames.
  Its sums are updated per frame at constant cost, so an estimate is available at any time whatever the history
  length; the 6x6 normal equations are solved through the 3x3 Schur complement. Feeding it a whole recording at once
  is the batch version.
- ``joint_track``: the joint centre in every frame from the two segments' poses, from one side when the other is
  occluded (Aristidou eq. 4.35).

Poses are (R, t) with R as (..., 3, 3) matrices or scipy ``Rotation``; NaN marks an unknown pose.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

HINGE_RATIO = 0.01
"""Smallest/largest eigenvalue ratio of the Schur block below which a joint is a hinge: its relative rotations spread
less than a tenth (in RMS angle) about one direction than about the main one, so the centre is a whole axis."""


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
    x, y = np.broadcast_arrays(x, y)
    w = np.isfinite(x).all(-1) & np.isfinite(y).all(-1)
    w = w * (1.0 if weights is None else np.asarray(weights, dtype=np.float64))
    x = np.where(w[..., None] > 0, x, 0.0)
    y = np.where(w[..., None] > 0, y, 0.0)
    s = np.einsum("...n,...na,...nb->...ab", w, x, y)  # S_ab = sum x_a y_b (Schoenauer 3.7.4)
    sxx, sxy, sxz = s[..., 0, 0], s[..., 0, 1], s[..., 0, 2]
    syx, syy, syz = s[..., 1, 0], s[..., 1, 1], s[..., 1, 2]
    szx, szy, szz = s[..., 2, 0], s[..., 2, 1], s[..., 2, 2]
    n = np.stack([
        np.stack([sxx + syy + szz, syz - szy, szx - sxz, sxy - syx], -1),
        np.stack([syz - szy, sxx - syy - szz, sxy + syx, szx + sxz], -1),
        np.stack([szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy], -1),
        np.stack([sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz], -1),
    ], -2)
    values, vectors = np.linalg.eigh(n)
    q = vectors[..., :, 3]  # Horn's (w, x, y, z) for the largest eigenvalue
    scale = np.abs(values).max(-1)
    gap = np.divide(values[..., 3] - values[..., 2], scale, out=np.zeros_like(scale), where=scale > 0)
    return np.concatenate([q[..., 1:], q[..., :1]], -1), gap


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


@dataclass
class PoseFit:
    """Per-frame poses of one segment: ``world = R @ local + t``; NaN where too few markers were visible."""

    rotations: np.ndarray  # (F, 4) scalar-last quaternions
    translations: np.ndarray  # (F, 3) mm
    residual: np.ndarray  # (F,) RMS distance between fitted and observed markers, mm
    determined: np.ndarray  # (F,) bool: the data fixed all three rotation angles

    def matrices(self) -> np.ndarray:
        """(F, 3, 3) rotation matrices, NaN where the pose is unknown."""
        return quaternion_matrices(self.rotations)

    def subset(self, frames: np.ndarray) -> PoseFit:
        """The poses of some frames only."""
        return PoseFit(self.rotations[frames], self.translations[frames], self.residual[frames],
                       self.determined[frames])


def quaternion_matrices(quaternions: np.ndarray) -> np.ndarray:
    """(..., 3, 3) matrices of scalar-last quaternions, NaN rows giving NaN matrices (scipy rejects NaN)."""
    q = np.asarray(quaternions, dtype=np.float64)
    known = np.isfinite(q).all(-1)
    out = np.full((*q.shape[:-1], 3, 3), np.nan)
    if known.any():
        out[known] = Rotation.from_quat(q[known]).as_matrix()
    return out


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
    """
    local = np.asarray(local, dtype=np.float64)
    obs = np.asarray(observed, dtype=np.float64)
    frames = obs.shape[0]
    seen = np.isfinite(obs).all(-1)
    count = seen.sum(1)
    seen_f = seen.astype(np.float64)
    safe = np.where(seen[..., None], obs, 0.0)
    origin_loc = np.einsum("fn,nk->fk", seen_f, local) / np.maximum(count, 1)[:, None]
    origin_obs = np.einsum("fn,fnk->fk", seen_f, safe) / np.maximum(count, 1)[:, None]
    free = np.ones(frames, bool)
    if pivot_local is not None and pivot_world is not None:
        pivot_world = np.asarray(pivot_world, dtype=np.float64)
        pinned = np.isfinite(pivot_world).all(-1)
        free = ~pinned
        origin_loc = np.where(pinned[:, None], np.asarray(pivot_local, dtype=np.float64), origin_loc)
        origin_obs = np.where(pinned[:, None], pivot_world, origin_obs)
    quats, gap = rotor(local[None] - origin_loc[:, None], obs - origin_obs[:, None])
    usable = np.where(free, count >= 2, count >= 1)
    quats[~usable] = np.nan
    determined = usable & (gap >= min_gap)
    if hold:
        _hold(quats, determined, local, obs, origin_loc, origin_obs)
    matrices = quaternion_matrices(quats)
    t = origin_obs - np.einsum("fab,fb->fa", matrices, origin_loc)
    fitted = np.einsum("fab,nb->fna", matrices, local) + t[:, None]
    err = np.where(seen, np.linalg.norm(fitted - obs, axis=-1) ** 2, 0.0).sum(1)
    residual = np.where(usable, np.sqrt(err / np.maximum(count, 1)), np.nan)
    return PoseFit(quats, t, residual, determined)


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


def _as_matrices(rotation: np.ndarray | Rotation) -> np.ndarray:
    if isinstance(rotation, Rotation):
        return rotation.as_matrix().reshape(-1, 3, 3)
    return np.asarray(rotation, dtype=np.float64).reshape(-1, 3, 3)


@dataclass
class CoREstimate:
    """A centre of rotation: the point in each segment's frame, the fit quality and the hinge test."""

    parent_offset: np.ndarray  # (3,) in the parent's frame, mm
    child_offset: np.ndarray  # (3,) in the child's frame, mm
    residual: float  # RMS distance between the joint as placed by the parent and by the child, mm
    ratio: float  # smallest/largest eigenvalue of the Schur block: near 0 for a hinge
    axis: np.ndarray  # (3,) unit direction of least relative rotation (the hinge axis), in the parent's frame
    child_axis: np.ndarray  # (3,) the same direction in the child's frame
    frames: int
    leverage: float  # mean squared misfit (mm^2) that moving the centre 1 mm along the axis adds (parent refitted)

    @property
    def is_hinge(self) -> bool:
        return self.ratio < HINGE_RATIO

    @property
    def axial_uncertainty(self) -> float:
        """Largest shift of the centre along the axis (mm) that a misfit as large as the residual can cause: the
        estimate moves by ``<J a, e> / |J a|^2 <= |e| / |J a|`` (Cauchy-Schwarz) for an artefact ``e``."""
        return self.residual / np.sqrt(self.leverage) if self.leverage > 0 else np.inf

    def __iter__(self) -> Iterator:
        """Unpacks as ``parent_offset, child_offset, residual = estimate``."""
        return iter((self.parent_offset, self.child_offset, self.residual))


class SequentialCoR:
    """Closed-form centre of rotation between two segments, updated frame by frame (Aristidou 4.4).

    Minimises ``sum_k |R_p p + t_p - R_c q - t_c|^2`` over the offsets ``p`` (parent frame) and ``q`` (child
    frame). The normal equations ``[[m I, -S], [-S^T, m I]] [p; q] = [-u; v]`` only involve the running sums
    ``m``, ``S = sum R_p^T R_c``, ``u = sum R_p^T d``, ``v = sum R_c^T d`` and ``sum |d|^2`` with
    ``d = t_p - t_c``, so each update and each estimate costs the same whatever the number of frames seen. The 6x6
    system is solved through the Schur complement ``m I - S^T S / m`` (3x3). When that block is nearly singular the
    joint is a hinge: every point of its axis is a solution, and the estimate is the minimum-norm one, the axis point
    at the mid-plane between the two segments' origins (their marker centroids).
    """

    def __init__(self, parent_reference: np.ndarray | None = None,
                 child_reference: np.ndarray | None = None) -> None:
        """References are the markers in each segment's frame, needed only by ``update_markers``; when absent, the
        first frame with every marker of both segments visible defines them (centred on their centroids)."""
        self.parent_reference = None if parent_reference is None else np.asarray(parent_reference, float)
        self.child_reference = None if child_reference is None else np.asarray(child_reference, float)
        self.m = 0
        self.s = np.zeros((3, 3))
        self.u = np.zeros(3)
        self.v = np.zeros(3)
        self.dd = 0.0

    def update(self, parent_r: np.ndarray | Rotation, parent_t: np.ndarray,
               child_r: np.ndarray | Rotation, child_t: np.ndarray) -> None:
        """Add one frame ((3, 3) or Rotation, (3,)) or many ((F, 3, 3), (F, 3)); frames with a NaN are skipped."""
        rp, rc = _as_matrices(parent_r), _as_matrices(child_r)
        d = np.asarray(parent_t, float).reshape(-1, 3) - np.asarray(child_t, float).reshape(-1, 3)
        ok = np.isfinite(rp).all((1, 2)) & np.isfinite(rc).all((1, 2)) & np.isfinite(d).all(1)
        rp, rc, d = rp[ok], rc[ok], d[ok]
        self.m += int(ok.sum())
        self.s += np.einsum("fba,fbc->ac", rp, rc)
        self.u += np.einsum("fba,fb->a", rp, d)
        self.v += np.einsum("fba,fb->a", rc, d)
        self.dd += float((d * d).sum())

    def update_markers(self, parent_markers: np.ndarray, child_markers: np.ndarray) -> None:
        """Add frames from marker positions ((n, 3) or (F, n, 3), NaN gaps): poses by ``fit_pose``."""
        pm = np.asarray(parent_markers, float).reshape(-1, *np.shape(parent_markers)[-2:])
        cm = np.asarray(child_markers, float).reshape(-1, *np.shape(child_markers)[-2:])
        if self.parent_reference is None or self.child_reference is None:
            full = np.isfinite(pm).all((1, 2)) & np.isfinite(cm).all((1, 2))
            if not full.any():
                return
            first = int(np.argmax(full))
            self.parent_reference = pm[first] - pm[first].mean(0)
            self.child_reference = cm[first] - cm[first].mean(0)
        parent = fit_pose(self.parent_reference, pm)
        child = fit_pose(self.child_reference, cm)
        keep = parent.determined & child.determined
        self.update(parent.matrices()[keep], parent.translations[keep], child.matrices()[keep],
                    child.translations[keep])

    def estimate(self) -> CoREstimate:
        """The current least-squares centre of rotation; raises ValueError before two frames were added."""
        if self.m < 2:
            raise ValueError("a centre of rotation needs at least two frames")
        m, s, u, v = float(self.m), self.s, self.u, self.v
        schur = m * np.eye(3) - s.T @ s / m
        values, vectors = np.linalg.eigh(schur)
        ratio = float(values[0] / values[2]) if values[2] > 0 else 0.0
        rhs = v - s.T @ u / m
        if ratio < HINGE_RATIO:
            inverse = (vectors[:, 1:] / values[1:]) @ vectors[:, 1:].T
        else:
            inverse = (vectors / values) @ vectors.T
        q = inverse @ rhs
        p = (s @ q - u) / m
        axis_child = vectors[:, 0]
        axis = s @ axis_child
        axis = axis / np.linalg.norm(axis) if np.linalg.norm(axis) > 0 else axis_child
        if ratio < HINGE_RATIO:  # slide along the axis to the minimum-norm point
            shift = -(p @ axis + q @ axis_child) / 2
            p, q = p + shift * axis, q + shift * axis_child
        sse = m * (p @ p + q @ q) - 2 * p @ s @ q + 2 * p @ u - 2 * q @ v + self.dd
        return CoREstimate(p, q, float(np.sqrt(max(sse, 0.0) / m)), ratio, axis, axis_child, self.m,
                           float(max(values[0], 0.0) / m))


def joint_track(parent_r: np.ndarray, parent_t: np.ndarray, child_r: np.ndarray, child_t: np.ndarray,
                parent_offset: np.ndarray, child_offset: np.ndarray) -> np.ndarray:
    """Joint centre per frame (F, 3): the mean of where each segment puts it (Aristidou eq. 4.29), or the one side
    whose pose is known when the other is occluded (eq. 4.35); NaN when neither is."""
    a = np.einsum("fab,b->fa", _as_matrices(parent_r), np.asarray(parent_offset, float)) + parent_t
    b = np.einsum("fab,b->fa", _as_matrices(child_r), np.asarray(child_offset, float)) + child_t
    both = np.stack([a, b])
    known = np.isfinite(both).all(-1)
    total = np.where(known[..., None], both, 0.0).sum(0)
    count = known.sum(0)[:, None]
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)
