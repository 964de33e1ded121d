"""Centres of rotation between two segments (Aristidou 2008, section 4.4).

Building blocks shared by calibration, the skeleton solver and joint tracking through occlusions (the rigid fits they
rest on are in ``rigidfit``):

- ``SequentialCoR``: the closed-form centre of rotation of Aristidou 4.4, the point fixed in both segments' frames.
  Its sums are updated per frame at constant cost, so an estimate is available at any time whatever the history
  length; the 6x6 normal equations are solved through the 3x3 Schur complement. Feeding it a whole recording at once
  is the batch version.
- ``joint_track``: the joint centre in every frame from the two segments' poses, from one side when the other is
  occluded (Aristidou eq. 4.35); ``joint_sides`` gives where each segment puts it.

Poses are (R, t) with R as (..., 3, 3) matrices or scipy ``Rotation``; NaN marks an unknown pose.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from mocapflow.mocap.rigidfit import fit_pose

HINGE_RATIO = 0.01
"""Smallest/largest eigenvalue ratio of the Schur block below which a joint is a hinge: its relative rotations spread
less than a tenth (in RMS angle) about one direction than about the main one, so the centre is a whole axis."""


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
        self.update(parent.rotation_matrices[keep], parent.translations[keep], child.rotation_matrices[keep],
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
    return side_mean(joint_sides(parent_r, parent_t, child_r, child_t, parent_offset, child_offset))


def joint_sides(parent_r: np.ndarray, parent_t: np.ndarray, child_r: np.ndarray, child_t: np.ndarray,
                parent_offset: np.ndarray, child_offset: np.ndarray) -> np.ndarray:
    """(2, F, 3): where the parent's pose and where the child's put the joint centre in each frame (NaN where that
    pose is unknown)."""
    a = np.einsum("fab,b->fa", _as_matrices(parent_r), np.asarray(parent_offset, float)) + parent_t
    b = np.einsum("fab,b->fa", _as_matrices(child_r), np.asarray(child_offset, float)) + child_t
    return np.stack([a, b])


def side_mean(both: np.ndarray) -> np.ndarray:
    """``joint_track`` from ``joint_sides``: the mean of the sides known in each frame."""
    known = np.isfinite(both).all(-1)
    total = np.where(known[..., None], both, 0.0).sum(0)
    count = known.sum(0)[:, None]
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)
