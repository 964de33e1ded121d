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

from mocapflow.mocap.model import SkeletonModel
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


def _place(matrices: np.ndarray, translations: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(F, S, 3) world positions of points at ``offsets`` (S, 3) in segments posed by (F, S, 3, 3) and (F, S, 3)."""
    return np.einsum("fsab,sb->fsa", matrices, offsets) + translations


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


class PoseSolver:
    """``solve`` for one skeleton and one label order, compiled once and reused frame after frame.

    Everything that depends on the model and the labels alone is worked out when the solver is built: the segments
    grouped by depth in the tree (all segments of one depth are fitted in one batched ``fit_pose`` call, as their
    parents are already posed), where in the positions and in the joints placed by children each segment's points
    are (index arrays, segments padded to a common size with a never-seen NaN column), the marker and joint offsets
    as arrays, and the distances trilateration needs. A call then only does the per-frame arithmetic. The cache is
    the solver itself: build a new one when the model or the labels change (the skeleton node keeps one while they
    do not)."""

    def __init__(self, skeleton: SkeletonModel, labels: Sequence[str]) -> None:
        for j in skeleton.joints:
            if j.parent_offset is None or j.child_offset is None:
                raise ValueError(f"joint {j.name!r} has no offsets: calibrate the skeleton first")
        for segment in skeleton.segments:
            if segment.marker_offsets is None:
                raise ValueError(f"segment {segment.name!r} has no marker offsets: calibrate the skeleton first")
        self.labels = list(labels)
        self.names = [s.name for s in skeleton.segments]
        self.joint_names = [j.name for j in skeleton.joints]
        index = {n: i for i, n in enumerate(self.names)}
        column = {label: i for i, label in enumerate(self.labels)}
        joints = skeleton.joints
        inner = {j.child: k for k, j in enumerate(joints)}  # segment -> index of the joint with its parent
        self.parents = [index[joints[inner[n]].parent] if n in inner else -1 for n in self.names]
        self.joint_parent = np.array([index[j.parent] for j in joints], dtype=np.intp)
        self.joint_child = np.array([index[j.child] for j in joints], dtype=np.intp)
        self.parent_offsets = np.array([j.parent_offset for j in joints], dtype=np.float64).reshape(-1, 3)
        self.child_offsets = np.array([j.child_offset for j in joints], dtype=np.float64).reshape(-1, 3)
        nan = len(self.labels)  # the NaN column appended to the positions: a marker not among the labels
        local = [np.asarray(s.marker_offsets, dtype=np.float64).reshape(-1, 3) for s in skeleton.segments]
        self.sizes = [len(m) for m in local]
        self.columns, self.local = _padded([[column.get(m, nan) for m in s.markers] for s in skeleton.segments],
                                           local, nan)
        # the tree by depth; a segment's points are its markers, then the joints its children place (columns after
        # the NaN one), in the segment's frame its marker offsets, then those joints' parent offsets
        self.levels: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        level = [index[skeleton.root]]
        while level:
            outer = [[k for k, j in enumerate(joints) if j.parent == self.names[s]] for s in level]
            columns, points_local = _padded(
                [[column.get(m, nan) for m in skeleton.segments[s].markers] + [nan + 1 + k for k in out]
                 for s, out in zip(level, outer, strict=True)],
                [np.concatenate([local[s], self.parent_offsets[out]]) for s, out in zip(level, outer, strict=True)],
                nan)
            self.levels.append((np.array(level, dtype=np.intp), np.array([inner.get(self.names[s], -1)
                                                                          for s in level], dtype=np.intp),
                                columns, points_local))
            level = [int(self.joint_child[k]) for out in outer for k in out]
        # trilateration of joint k: its distances to the markers of both segments and to the parent's own joint
        self.up = [inner.get(j.parent, -1) for j in joints]
        self.radii = [np.concatenate([
            np.linalg.norm(local[self.joint_parent[k]] - self.parent_offsets[k], axis=1),
            np.linalg.norm(local[self.joint_child[k]] - self.child_offsets[k], axis=1),
            [np.linalg.norm(self.child_offsets[self.up[k]] - self.parent_offsets[k])] if self.up[k] >= 0 else []])
            for k in range(len(joints))]
        self.least_own = [2 if up >= 0 else 3 for up in self.up]

    def __call__(self, positions: np.ndarray, progress: Progress | None = None) -> SkeletonPose:
        """The pose in every frame of (F, N, 3) trajectories in the solver's label order (NaN gaps)."""
        positions = np.asarray(positions, dtype=np.float64)
        frames = positions.shape[0]
        padded = np.concatenate([positions, np.full((frames, 1, 3), np.nan)], axis=1)
        observed = padded[:, self.columns]  # (F, S, n, 3)
        children = self.joint_child
        alone = fit_pose(self.local[children], observed[:, children])
        placed = np.where(alone.determined[..., None], _place(alone.rotation_matrices, alone.translations,
                                                              self.child_offsets), np.nan)
        matrices, translations, rotations, residual, fit = self._top_down(padded, observed, placed, progress)
        centres = self._centres(matrices, translations)
        # a parent showing too few points of its own, whose child's markers cannot place their joint either (fewer
        # than three visible), gets that joint where its distances to every visible marker of both segments and to
        # the parent's own joint are right, and is fitted again with it
        again = False
        visible = np.isfinite(observed).all(-1).sum(-1)
        for k, (p, c) in enumerate(zip(self.joint_parent, children, strict=True)):
            short = visible[:, p] < self.least_own[k]
            if not short.any():
                continue
            points = [observed[short, p, :self.sizes[p]], observed[short, c, :self.sizes[c]]]
            if self.up[k] >= 0:
                points.append(centres[short][:, [self.up[k]]])
            found = trilaterate(np.concatenate(points, axis=1), self.radii[k], centres[short, k])
            fill = np.isnan(placed[short, k]) & np.isfinite(found)
            if fill.any():
                again = True
                placed[short, k] = np.where(fill, found, placed[short, k])
        if again:
            matrices, translations, rotations, residual, fit = self._top_down(padded, observed, placed, progress)
            centres = self._centres(matrices, translations)
        return SkeletonPose(self.names, self.joint_names, self.parents, rotations, translations, centres, residual,
                            fit)

    def _top_down(self, padded: np.ndarray, observed: np.ndarray, placed: np.ndarray, progress: Progress | None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        """Every segment fitted from the root down, a depth at a time: matrices, translations, quaternions,
        residuals (F, S) and the mean marker fit."""
        frames, count = padded.shape[0], len(self.names)
        matrices = np.full((frames, count, 3, 3), np.nan)
        rotations = np.full((frames, count, 4), np.nan)
        translations = np.full((frames, count, 3), np.nan)
        determined = np.zeros((frames, count), bool)
        sources = np.concatenate([padded, placed], axis=1)
        for segments, joints, columns, points_local in steps(self.levels, len(self.levels), "solve", progress):
            points = sources[:, columns]
            pivot_local = pivot_world = None
            if joints[0] >= 0:  # below the root: each turns about the joint its parent places
                p = self.joint_parent[joints]
                pivot_local = self.child_offsets[joints]
                pivot_world = _place(matrices[:, p], translations[:, p], self.parent_offsets[joints])
                own = np.isfinite(points).all(-1).sum(-1) >= 3
                pivot_world[~determined[:, p] & own] = np.nan
            fit = fit_pose(points_local, points, pivot_local, pivot_world, hold=True)
            rotations[:, segments], translations[:, segments] = fit.rotations, fit.translations
            determined[:, segments], matrices[:, segments] = fit.determined, fit.rotation_matrices
        fitted = np.einsum("fsab,snb->fsna", matrices, self.local) + translations[:, :, None]
        seen = np.isfinite(observed).all(-1)
        err = np.where(seen, ((fitted - observed) ** 2).sum(-1), 0.0)
        residual = np.where(seen.any(-1), np.sqrt(err.sum(-1) / np.maximum(seen.sum(-1), 1)), np.nan)
        every = np.sqrt(err[seen & np.isfinite(err)])
        return matrices, translations, rotations, residual, float(every.mean()) if len(every) else np.nan

    def _centres(self, matrices: np.ndarray, translations: np.ndarray) -> np.ndarray:
        """(F, J, 3) joint centres: ``joint_track`` of every joint at once."""
        p, c = self.joint_parent, self.joint_child
        a = _place(matrices[:, p], translations[:, p], self.parent_offsets)
        b = _place(matrices[:, c], translations[:, c], self.child_offsets)
        known_a, known_b = np.isfinite(a).all(-1, keepdims=True), np.isfinite(b).all(-1, keepdims=True)
        total = np.where(known_a, a, 0.0) + np.where(known_b, b, 0.0)
        count = known_a.astype(np.float64) + known_b
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def _padded(columns: list[list[int]], local: list[np.ndarray], nan: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-segment point columns and local points as (S, n) and (S, n, 3) arrays padded to the longest with the NaN
    column and zeros (points never seen)."""
    size = max((len(c) for c in columns), default=0)
    out_columns = np.full((len(columns), size), nan, dtype=np.intp)
    out_local = np.zeros((len(columns), size, 3))
    for s, (c, x) in enumerate(zip(columns, local, strict=True)):
        out_columns[s, :len(c)], out_local[s, :len(c)] = c, x
    return out_columns, out_local


def solve(skeleton: SkeletonModel, positions: np.ndarray, labels: Sequence[str], *,
          progress: Progress | None = None) -> SkeletonPose:
    """Pose the rigid ``skeleton`` in every frame of (F, N, 3) labelled trajectories (NaN gaps).

    Each segment is fitted to its visible markers plus, like Schoenauer's implementation, the joints it shares with
    its children wherever a child's own markers place them; non-root segments turn about the joint placed by their
    parent. Where the parent's pose was not fixed by data in a frame and the segment has three points of its own, it
    is fitted freely instead, so that a guessed orientation does not spread down the chain. Markers of the skeleton
    missing from ``labels`` count as never seen. Raises ValueError when the skeleton is not calibrated (no offsets).
    A caller solving frame after frame with the same model and labels keeps a ``PoseSolver`` instead.
    """
    return PoseSolver(skeleton, labels)(positions, progress)
