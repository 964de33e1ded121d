"""Joint centres down the skeleton's tree, for calibration (Aristidou's sequential centres of rotation, extended to
segments of two markers): between two posed segments the closed-form centre of rotation; between a posed segment and
one whose markers do not fix its orientation, the centre of the spheres the latter's markers run on."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mocapflow.mocap.cor import CoREstimate, SequentialCoR, joint_track
from mocapflow.mocap.joints import fit_joint_variance, marker_centroid
from mocapflow.mocap.report import Progress, steps
from mocapflow.mocap.rigid import fit_shape
from mocapflow.mocap.rigidfit import PoseFit

MIN_TOGETHER = 10
"""Fewest frames in which two segments must both be posed for a centre of rotation between them."""


def closed_form(parent: PoseFit, child: PoseFit) -> CoREstimate:
    """The closed-form centre of rotation between two segments from their poses in every frame (Aristidou 4.4)."""
    cor = SequentialCoR()
    cor.update(parent.rotation_matrices, parent.translations, child.rotation_matrices, child.translations)
    return cor.estimate()


def sphere_centre(points: np.ndarray, prior: np.ndarray, damping: float = 1e-3) -> np.ndarray:
    """The point that keeps a constant distance to each of the (F, K, 3) trajectories, each on a sphere of its own:
    the algebraic least-squares centre (``2 p . c + d_k = |p|^2``, the per-sphere constants eliminated by centring
    each trajectory), held near ``prior`` only along directions the data leave free (a hinge's axis): ``damping``
    is relative to the data's own weight."""
    rows, rhs = [], []
    for k in range(points.shape[1]):
        p = points[np.isfinite(points[:, k]).all(-1), k]
        if len(p) < 2:
            continue
        sq = (p * p).sum(1)
        rows.append(2 * (p - p.mean(0)))
        rhs.append(sq - sq.mean())
    if not rows:
        return np.asarray(prior, dtype=np.float64)
    a, b = np.concatenate(rows), np.concatenate(rhs)
    normal = a.T @ a
    weight = damping * np.trace(normal) / 3 + 1e-9
    return np.linalg.solve(normal + weight * np.eye(3), a.T @ b + weight * np.asarray(prior, dtype=np.float64))


def _in_frame(pose: PoseFit, points: np.ndarray) -> np.ndarray:
    """(F, K, 3) world points in a segment's frame, NaN where its pose is unknown."""
    return np.einsum("fba,fkb->fka", pose.rotation_matrices, points - pose.translations[:, None])


def _sphere_track(pose: PoseFit, own: np.ndarray, other: np.ndarray) -> np.ndarray | None:
    """Joint centre per frame from a posed segment (its markers ``own``) and the markers ``other`` of a segment
    whose orientation is unknown: the centre of the spheres ``other`` runs on in the posed segment's frame, held
    along a free axis near the point between the two segments' closest markers. None when no frame shows both."""
    other_local, own_local = _in_frame(pose, other), _in_frame(pose, own)
    seen_other, seen_own = np.isfinite(other_local).all(-1), np.isfinite(own_local).all(-1)
    if seen_other.sum() < MIN_TOGETHER or not seen_own.any():
        return None
    mean_other = np.where(seen_other, 1, 0)[..., None] * np.nan_to_num(other_local)
    mean_other = mean_other.sum(0) / np.maximum(seen_other.sum(0), 1)[:, None]
    mean_own = (np.where(seen_own, 1, 0)[..., None] * np.nan_to_num(own_local)).sum(0)
    mean_own = mean_own / np.maximum(seen_own.sum(0), 1)[:, None]
    gap = np.linalg.norm(mean_other[:, None] - mean_own[None], axis=-1)
    gap[~seen_other.any(0)] = np.inf
    gap[:, ~seen_own.any(0)] = np.inf
    i, j = np.unravel_index(np.argmin(gap), gap.shape)
    centre = sphere_centre(other_local, (mean_other[i] + mean_own[j]) / 2)
    return np.einsum("fab,b->fa", pose.rotation_matrices, centre) + pose.translations


def sequential_tracks(positions: np.ndarray, groups: Sequence[Sequence[int]], poses: Sequence[PoseFit | None],
                       edges: Sequence[tuple[int, int]], reference: int, progress: Progress | None
                       ) -> dict[tuple[int, int], np.ndarray]:
    """Joint centres (F, 3) down the tree from an oriented root (Aristidou's sequential centres of rotation,
    extended to segments of two markers). Between two posed segments: the closed-form centre of rotation. Between a
    posed segment and one whose markers do not fix its orientation: the centre of the spheres the latter's markers
    run on in the posed segment's frame; that joint and its two markers then pose it for its own children."""
    posed = list(poses)
    tracks = {}
    for parent, child in steps(edges, len(edges), "joints", progress):
        pp, pc = posed[parent], posed[child]
        mp, mc = positions[:, list(groups[parent])], positions[:, list(groups[child])]
        together = pp is not None and pc is not None and int(
            (np.isfinite(pp.rotations).all(1) & np.isfinite(pc.rotations).all(1)).sum()) >= MIN_TOGETHER
        track: np.ndarray | None = None
        if together and pp is not None and pc is not None:
            est = closed_form(pp, pc)
            track = joint_track(pp.rotation_matrices, pp.translations, pc.rotation_matrices, pc.translations,
                                est.parent_offset, est.child_offset)
        elif pp is not None or pc is not None:  # the better posed of the two carries the other's spheres
            if pp is not None and (pc is None or np.isfinite(pp.rotations).all(1).sum() >=
                                   np.isfinite(pc.rotations).all(1).sum()):
                track = _sphere_track(pp, mp, mc)
            elif pc is not None:
                track = _sphere_track(pc, mc, mp)
        else:  # neither posed (a chain of two-marker segments under one in a line)
            track = None
        if track is None:  # nothing poses either side: Schoenauer's variance cost
            both = np.concatenate([mp, mc], axis=1)
            track = fit_joint_variance(both, marker_centroid(both), max_iterations=30).centres
        tracks[parent, child] = track
        if pc is None:
            try:
                posed[child] = fit_shape(mc, track[:, None], reference=reference).pose
            except ValueError:
                posed[child] = None
    return tracks
