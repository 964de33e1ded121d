"""Rigid parameters of segments (Schoenauer 2007, 3.8.1): marker and joint offsets averaged over many frames.

Each segment is lined up with its reference-frame shape in every usable frame by Horn's method (``rigidfit.fit_pose``);
the markers and joint centres then form a cloud of positions per point in the segment frame. Frames whose fit
residual is far above the typical one are dropped, and in each cloud the samples farther from the mean than the
cloud's standard deviation are dropped before averaging again. The averages are the segment's marker offsets and its
joint offsets, in the frame of ``model.py``: origin at the markers' centroid, axes parallel to the world in the
reference frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocapflow.mocap.model import SkeletonModel
from mocapflow.mocap.rigidfit import PoseFit, fit_pose

RESIDUAL_MADS = 4.0
"""A frame is an outlier when its fit residual exceeds the median by this many (normal-scaled) MADs."""


@dataclass
class SegmentShape:
    """A segment's averaged shape and its pose in every frame."""

    marker_offsets: np.ndarray  # (n, 3) in the segment frame
    extra_offsets: np.ndarray  # (k, 3) joint centres in the segment frame
    pose: PoseFit  # per frame, against marker_offsets (and extra_offsets when the markers alone do not suffice);
    # NaN where the visible points do not fix all three angles
    frames_used: int
    in_line: bool = False  # the points lie on a line: the turn about it is held from frame to frame, not measured

    @property
    def marker_spread(self) -> np.ndarray:
        """(n,) RMS distance of each marker from where the segment's pose puts it, over the frames posed (mm): how
        far skin, soft tissue or a joint inside the segment moves it off the rigid layout. A marker never seen in a
        posed frame is given the largest spread of the others (0 when none was seen)."""
        n = len(self.marker_offsets)
        fitted = np.einsum("fab,nb->fna", self.pose.rotation_matrices, self.marker_offsets)
        err = np.linalg.norm(fitted + self.pose.translations[:, None] - self.pose.observed[:, :n], axis=-1)
        seen = np.isfinite(err)
        count = seen.sum(0)
        spread = np.sqrt(np.where(seen, err * err, 0.0).sum(0) / np.maximum(count, 1))
        return np.where(count > 0, spread, spread[count > 0].max(initial=0.0))


def robust_mean(cloud: np.ndarray) -> np.ndarray:
    """Mean of a (F, 3) cloud after dropping samples farther from the first mean than its standard deviation
    (Schoenauer 3.8.1 step 4); NaN samples are ignored."""
    cloud = cloud[np.isfinite(cloud).all(1)]
    if len(cloud) == 0:
        return np.full(3, np.nan)
    mean = cloud.mean(0)
    dist = np.linalg.norm(cloud - mean, axis=1)
    sigma = np.sqrt((dist ** 2).mean())
    keep = dist <= sigma
    return cloud[keep].mean(0) if keep.any() else mean


def inlier_frames(residual: np.ndarray) -> np.ndarray:
    """Frames whose fit residual is not an outlier (median + ``RESIDUAL_MADS`` scaled MADs); NaN residuals excluded."""
    finite = np.isfinite(residual)
    if not finite.any():
        return finite
    med = np.median(residual[finite])
    mad = 1.4826 * np.median(np.abs(residual[finite] - med))
    return finite & (residual <= med + RESIDUAL_MADS * max(mad, 1e-9))


def fit_shape(markers: np.ndarray, extras: np.ndarray | None = None, reference: int | None = None,
              iterations: int = 2) -> SegmentShape:
    """Averaged marker (and joint) offsets of one segment from (F, n, 3) markers and (F, k, 3) joint centres.

    The pose is fitted on the markers when there are at least three, else on markers and joint centres together
    (Schoenauer treats both alike, which lets a two-marker segment turn about its marker line). Each frame's pose
    comes from whatever points it shows, so a segment never seen whole is still measured. ``reference`` is the frame
    whose orientation defines the axes (when another frame shows more points: the first frame showing the most);
    when no frame shows every point, the first shape comes from the mean distances between the points
    (``_shape_from_distances``). The shape is refitted ``iterations`` times against the averaged one (generalised
    Procrustes). Points in a line (two markers and a joint on the segment's long axis) leave its turn about the
    line free: it is held from frame to frame, which moves none of the points. Raises ValueError when no frame
    shows enough points to place the segment, or a point is never seen in a frame that does.
    """
    markers = np.asarray(markers, dtype=np.float64)
    frames, n, _ = markers.shape
    extras = np.zeros((frames, 0, 3)) if extras is None else np.asarray(extras, dtype=np.float64)
    points = np.concatenate([markers, extras], axis=1)
    fit_count = n if n >= 3 else points.shape[1]
    seen = np.isfinite(points).all(-1)
    shown = seen[:, :fit_count].sum(1) * (seen.shape[1] + 1) + seen.sum(1)  # the fitted points first
    ref = reference if reference is not None and shown[reference] == shown.max() else int(np.argmax(shown))
    shape = points[ref] if seen[ref].all() else _shape_from_distances(points, seen, ref, fit_count)
    shape = shape - shape[:n].mean(0)
    line = False  # points in a line: their turn about it is held from frame to frame, which moves none of them
    for _ in range(iterations):
        pose = fit_pose(shape[:fit_count], points[:, :fit_count], hold=line)
        if not line and not pose.determined.any():
            line = True
            pose = fit_pose(shape[:fit_count], points[:, :fit_count], hold=True)
        posed = np.isfinite(pose.rotations).all(1) if line else pose.determined
        used = posed & inlier_frames(pose.residual)
        if not used.any():
            raise ValueError("no frame shows enough of the segment's points to place it")
        local = np.einsum("fba,fnb->fna", pose.rotation_matrices[used], points[used] - pose.translations[used, None])
        shape = np.stack([robust_mean(local[:, j]) for j in range(points.shape[1])])
        if not np.isfinite(shape).all():
            raise ValueError("a point of the segment is never seen in a frame that fixes its orientation")
        shape -= shape[:n].mean(0)
    pose = fit_pose(shape[:fit_count], points[:, :fit_count], hold=line)
    if not line:
        pose.rotations[~pose.determined] = np.nan
        pose.translations[~pose.determined] = np.nan
    return SegmentShape(shape[:n], shape[n:], pose, int(used.sum()), line)


def _shape_from_distances(points: np.ndarray, seen: np.ndarray, ref: int, fit_count: int) -> np.ndarray:
    """A segment's shape, in the orientation of frame ``ref``, from the mean distance of every two of its points
    (classical multidimensional scaling), for a segment that no frame shows whole. Distances cannot tell a shape from
    its mirror image, and a frame showing three points fits either: the one kept is the one whose poses turn less
    from frame to frame (the mirror image jumps whenever the set of visible points changes)."""
    both = seen[:, :, None] & seen[:, None, :]
    diff = np.linalg.norm(points[:, :, None] - points[:, None, :], axis=-1)
    count = both.sum(0)
    if (count == 0).any():
        raise ValueError("no frame shows every marker and joint of the segment, and some two of them are never "
                         "seen together")
    sq = (np.where(both, diff, 0.0).sum(0) / count) ** 2
    k = len(sq)
    centre = np.eye(k) - 1.0 / k
    values, vectors = np.linalg.eigh(-0.5 * centre @ sq @ centre)
    shape = vectors[:, ::-1][:, :3] * np.sqrt(np.maximum(values[::-1][:3], 0.0))
    fits = [fit_pose(s[:fit_count], points[:, :fit_count]) for s in (shape, shape * [1.0, 1.0, -1.0])]
    best = int(_turning(fits[1]) < _turning(fits[0]))
    pose = fits[best]
    if not pose.determined[ref]:
        raise ValueError("no frame fixes the segment's orientation (its points are in a line)")
    return np.einsum("ab,nb->na", pose.rotation_matrices[ref], shape * ([1.0, 1.0, -1.0] if best else 1.0))


def _turning(pose: PoseFit) -> float:
    """Mean rotation (rad) between consecutive frames whose orientation is fixed."""
    q = pose.rotations[pose.determined]
    if len(q) < 2:
        return 0.0
    return float(np.mean(2 * np.arccos(np.clip(np.abs((q[1:] * q[:-1]).sum(1)), 0.0, 1.0))))


def bone_lengths(skeleton: SkeletonModel) -> dict[tuple[str, str], float]:
    """Distance (mm) between every two joints on the same segment, keyed by the two joint names: a bone's length
    when the segment has one joint at each end."""
    on_segment: dict[str, list[tuple[str, np.ndarray]]] = {}
    for j in skeleton.joints:
        if j.parent_offset is None or j.child_offset is None:
            raise ValueError(f"joint {j.name!r} has no offsets: calibrate the skeleton first")
        on_segment.setdefault(j.parent, []).append((j.name, np.asarray(j.parent_offset)))
        on_segment.setdefault(j.child, []).append((j.name, np.asarray(j.child_offset)))
    return {(a, b): float(np.linalg.norm(pa - pb))
            for joints in on_segment.values() for i, (a, pa) in enumerate(joints) for b, pb in joints[i + 1:]}
