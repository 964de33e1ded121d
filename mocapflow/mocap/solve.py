"""Fit a calibrated rigid skeleton to marker data, frame by frame (Schoenauer 2007, 3.8.2).

The root is aligned with its markers by Horn's method; every other segment, from the root down, only rotates about
its joint with its parent, which stays where the parent puts it, so the skeleton never comes apart. Like the thesis's
implementation, a segment's fit also uses the joints its children's own markers place. A segment is posed in a frame
when it has one point (marker, or joint placed by a child) besides its pivot, or two without one; when the points fix
only one direction the rotation is the one closest to the previous frame's that matches it
(``cor.fit_pose(hold=True)``).

The result holds everything a motion file needs: world rotations and origins of every segment and the joint centres,
per frame; ``local_rotations`` gives each segment's rotation relative to its parent (what BVH channels store).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from mocapflow.mocap.cor import joint_track
from mocapflow.mocap.model import Segment, SkeletonModel
from mocapflow.mocap.report import Progress, steps
from mocapflow.mocap.rigidfit import fit_pose, quaternion_matrices


@dataclass
class SkeletonPose:
    """A skeleton's motion: per frame, each segment's pose (``world = R @ local + t``) and each joint's centre."""

    segment_names: list[str]
    joint_names: list[str]
    parents: list[int]  # per segment: index of its parent segment, -1 for the root
    rotations: np.ndarray  # (F, S, 4) scalar-last quaternions, NaN where the segment could not be posed
    translations: np.ndarray  # (F, S, 3) segment origins in mm
    joint_centres: np.ndarray  # (F, J, 3) mm
    residual: np.ndarray  # (F, S) RMS distance between fitted and observed markers, mm
    marker_fit: float = float("nan")  # mean distance between fitted and observed markers over every seen sample, mm

    def local_rotations(self) -> np.ndarray:
        """(F, S, 4) rotation of each segment relative to its parent (the root's is its world rotation)."""
        world = quaternion_matrices(self.rotations)
        parent = world[:, [p if p >= 0 else s for s, p in enumerate(self.parents)]]
        local = np.where(np.array([p >= 0 for p in self.parents])[None, :, None, None],
                         np.einsum("fsba,fsbc->fsac", parent, world), world)
        out = np.full(self.rotations.shape, np.nan)
        known = np.isfinite(local).all((-1, -2))
        if known.any():
            out[known] = Rotation.from_matrix(local[known]).as_quat()
        return out


def _observed(segment: Segment, positions: np.ndarray, column: dict[str, int]) -> tuple[np.ndarray, np.ndarray]:
    """A segment's marker offsets (n, 3) and their observed trajectories (F, n, 3), NaN for absent labels."""
    if segment.marker_offsets is None:
        raise ValueError(f"segment {segment.name!r} has no marker offsets: calibrate the skeleton first")
    observed = np.full((positions.shape[0], len(segment.markers), 3), np.nan)
    for k, label in enumerate(segment.markers):
        if label in column:
            observed[:, k] = positions[:, column[label]]
    return np.asarray(segment.marker_offsets, dtype=np.float64), observed


def _place(matrices: np.ndarray, translations: np.ndarray, offset: Sequence[float] | None) -> np.ndarray:
    if offset is None:
        raise ValueError("a joint without offsets: calibrate the skeleton first")
    return np.einsum("fab,b->fa", matrices, np.asarray(offset, dtype=np.float64)) + translations


def trilaterate(points: np.ndarray, radii: np.ndarray, start: np.ndarray, iterations: int = 10,
                least: int = 4) -> np.ndarray:
    """Per frame, the point whose distances to the visible (F, K, 3) ``points`` are the (K,) ``radii`` (least
    squares, damped Gauss-Newton from ``start``); NaN where fewer than ``least`` points are visible or no start."""
    seen = np.isfinite(points).all(-1)
    ok = (seen.sum(1) >= least) & np.isfinite(start).all(1)
    x = np.where(ok[:, None], start, 0.0)
    safe = np.where(seen[..., None], points, 0.0)
    for _ in range(iterations):
        diff = x[:, None] - safe
        dist = np.maximum(np.linalg.norm(diff, axis=-1), 1e-9)
        unit = np.where(seen[..., None], diff / dist[..., None], 0.0)
        res = np.where(seen, dist - radii, 0.0)
        normal = np.einsum("fki,fkj->fij", unit, unit) + 1e-6 * np.eye(3)
        x = x - np.linalg.solve(normal, np.einsum("fki,fk->fi", unit, res)[..., None])[..., 0]
    return np.where(ok[:, None], x, np.nan)


def _trilaterate_joint(skeleton: SkeletonModel, k: int, data: list[tuple[np.ndarray, np.ndarray]],
                       index: dict[str, int], inner: dict, centres: np.ndarray) -> np.ndarray:
    """Joint ``k`` placed from its known distances to the markers of its two segments and to the parent's own
    joint (as the first pass placed it), starting from the first pass's centre."""
    joint = skeleton.joints[k]
    (p_local, p_seen), (c_local, c_seen) = data[index[joint.parent]], data[index[joint.child]]
    p_off, c_off = np.asarray(joint.parent_offset), np.asarray(joint.child_offset)
    points = [p_seen, c_seen]
    radii = [np.linalg.norm(p_local - p_off, axis=1), np.linalg.norm(c_local - c_off, axis=1)]
    if joint.parent in inner:
        up = inner[joint.parent]
        points.append(centres[:, [skeleton.joints.index(up)]])
        radii.append([np.linalg.norm(np.asarray(up.child_offset) - p_off)])
    return trilaterate(np.concatenate(points, axis=1), np.concatenate(radii), centres[:, k])


def solve(skeleton: SkeletonModel, positions: np.ndarray, labels: Sequence[str], *,
          progress: Progress | None = None) -> SkeletonPose:
    """Pose the rigid ``skeleton`` in every frame of (F, N, 3) labelled trajectories (NaN gaps).

    Each segment is fitted to its visible markers plus, like Schoenauer's implementation, the joints it shares with
    its children wherever a child's own markers place them; non-root segments turn about the joint placed by their
    parent. Where the parent's pose was not fixed by data in a frame and the segment has three points of its own, it
    is fitted freely instead, so that a guessed orientation does not spread down the chain. Markers of the skeleton
    missing from ``labels`` count as never seen. Raises ValueError when the skeleton is not calibrated (no offsets).
    """
    positions = np.asarray(positions, dtype=np.float64)
    frames = positions.shape[0]
    column = {label: i for i, label in enumerate(labels)}
    names = [s.name for s in skeleton.segments]
    index = {n: i for i, n in enumerate(names)}
    for j in skeleton.joints:
        if j.parent_offset is None or j.child_offset is None:
            raise ValueError(f"joint {j.name!r} has no offsets: calibrate the skeleton first")
    inner = {j.child: j for j in skeleton.joints}
    parents = [index[inner[n].parent] if n in inner else -1 for n in names]
    order = [index[skeleton.root]]
    for s in order:
        order += [index[j.child] for j in skeleton.joints if j.parent == names[s]]
    data = [_observed(segment, positions, column) for segment in skeleton.segments]
    alone = [fit_pose(local, observed) for local, observed in data]
    placed = [np.where(alone[index[j.child]].determined[:, None], _place(
        alone[index[j.child]].matrices(), alone[index[j.child]].translations, j.child_offset), np.nan)
        for j in skeleton.joints]

    def top_down(placed: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        distances = []
        rotations = np.full((frames, len(names), 4), np.nan)
        translations = np.full((frames, len(names), 3), np.nan)
        residual = np.full((frames, len(names)), np.nan)
        determined = np.zeros((frames, len(names)), bool)
        for s in steps(order, len(order), "solve", progress):
            local, observed = data[s]
            outer = [k for k, j in enumerate(skeleton.joints) if j.parent == names[s]]
            extra_local = np.array([skeleton.joints[k].parent_offset for k in outer]).reshape(-1, 3)
            extra_world = np.stack([placed[k] for k in outer], axis=1) if outer else np.zeros((frames, 0, 3))
            points_local = np.concatenate([local, extra_local])
            points = np.concatenate([observed, extra_world], axis=1)
            pivot_local = pivot_world = None
            if parents[s] >= 0:
                joint, p = inner[names[s]], parents[s]
                pivot_local = np.asarray(joint.child_offset, dtype=np.float64)
                pivot_world = _place(quaternion_matrices(rotations[:, p]), translations[:, p], joint.parent_offset)
                own = np.isfinite(points).all(-1).sum(1) >= 3
                pivot_world[~determined[:, p] & own] = np.nan
            fit = fit_pose(points_local, points, pivot_local, pivot_world, hold=True)
            rotations[:, s], translations[:, s], determined[:, s] = fit.rotations, fit.translations, fit.determined
            fitted = np.einsum("fab,nb->fna", fit.matrices(), local) + fit.translations[:, None]
            seen = np.isfinite(observed).all(-1)
            err = np.where(seen, ((fitted - observed) ** 2).sum(-1), 0.0)
            residual[:, s] = np.where(seen.any(1), np.sqrt(err.sum(1) / np.maximum(seen.sum(1), 1)), np.nan)
            distances.append(np.sqrt(err[seen & np.isfinite(err)]))
        every = np.concatenate(distances) if distances else np.zeros(0)
        return rotations, translations, residual, determined, float(every.mean()) if len(every) else np.nan

    def centres_of(rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
        matrices = quaternion_matrices(rotations)
        return np.stack([
            joint_track(matrices[:, index[j.parent]], translations[:, index[j.parent]], matrices[:, index[j.child]],
                        translations[:, index[j.child]], np.asarray(j.parent_offset), np.asarray(j.child_offset))
            for j in skeleton.joints], axis=1) if skeleton.joints else np.zeros((frames, 0, 3))

    rotations, translations, residual, determined, fit = top_down(placed)
    centres = centres_of(rotations, translations)
    # a parent showing too few points of its own, whose child's markers cannot place their joint either (fewer than
    # three visible), gets that joint where its distances to every visible marker of both segments and to the
    # parent's own joint are right, and is fitted again with it
    found = []
    for k, j in enumerate(skeleton.joints):
        short = np.isfinite(data[index[j.parent]][1]).all(-1).sum(1) < (2 if j.parent in inner else 3)
        found.append(np.where(short[:, None], _trilaterate_joint(skeleton, k, data, index, inner, centres), np.nan))
    if any(np.isfinite(f).any() for f in found):
        placed = [np.where(np.isfinite(p), p, f) for p, f in zip(placed, found, strict=True)]
        rotations, translations, residual, determined, fit = top_down(placed)
        centres = centres_of(rotations, translations)
    return SkeletonPose(names, [j.name for j in skeleton.joints], parents, rotations, translations, centres, residual,
                        fit)
