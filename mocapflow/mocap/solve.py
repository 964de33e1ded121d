"""Fit a calibrated rigid skeleton to marker data, frame by frame (Schoenauer 2007, 3.8.2).

The root is aligned with its markers by Horn's method; every other segment, from the root down, only rotates about
its joint with its parent, which stays where the parent puts it, so the skeleton never comes apart. Like the thesis's
implementation, a segment's fit also uses the joints its children's own markers place. A segment is posed in a frame
when it has one point (marker, or joint placed by a child) besides its pivot, or two without one; when the points fix
only one direction the rotation is the one closest to the previous frame's turn from its parent that matches it
(``rigidfit.hold_turns``: the parent carries it), and for a segment that no frame fixes, the one closest to its
parent's.

The result holds everything a motion file needs: world rotations and origins of every segment and the joint centres,
per frame; ``local_rotations`` gives each segment's rotation relative to its parent (what BVH channels store).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.spatial.transform import Rotation

from mocapflow.mocap.model import SkeletonModel
from mocapflow.mocap.report import Progress
from mocapflow.mocap.rigidfit import (
    MIN_GAP,
    det3,
    finite,
    fit_frame,
    hold_turns,
    place,
    pose_matrix,
    quaternion_matrices,
    relative_turn,
)


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


class PoseSolver:
    """``solve`` for one skeleton and one label order, compiled once and reused frame after frame.

    Everything that depends on the model and the labels alone is worked out when the solver is built, as arrays: the
    segments in tree order (each after its parent), where in the positions and in the joints placed by children each
    segment's points are (index arrays, segments padded to a common size with a never-seen NaN column), the marker
    and joint offsets, and the distances trilateration needs. A call then runs the per-frame arithmetic, compiled
    (numba): one live frame costs tens of microseconds, where the same steps as numpy operations cost milliseconds in
    per-call overhead. The cache is the solver itself: build a new one when the model or the labels change (the
    skeleton node keeps one while they do not).

    A kept solver also remembers, per segment, its turn from its parent in the last frame whose points fixed it, from
    earlier calls: a frame whose points fix one direction only holds from there, as one call over a whole recording
    holds from the frames before, so that live (a frame or a few a call) a segment seen through one marker and its
    joint keeps turning plausibly instead of taking an arbitrary, chaotic turn about them."""

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
        nan = len(self.labels)  # the NaN column appended to the positions: a marker not among the labels
        local = [np.asarray(s.marker_offsets, dtype=np.float64).reshape(-1, 3) for s in skeleton.segments]
        parent_offsets = np.array([j.parent_offset for j in joints], dtype=np.float64).reshape(-1, 3)
        child_offsets = np.array([j.child_offset for j in joints], dtype=np.float64).reshape(-1, 3)
        columns, marker_local = _padded([[column.get(m, nan) for m in s.markers] for s in skeleton.segments], local,
                                        nan)
        # a segment's points are its markers, then the joints its children place (columns after the NaN one), in
        # the segment's frame its marker offsets, then those joints' parent offsets
        outer = [[k for k, j in enumerate(joints) if j.parent == name] for name in self.names]
        point_columns, point_local = _padded(
            [[column.get(m, nan) for m in s.markers] + [nan + 1 + k for k in out]
             for s, out in zip(skeleton.segments, outer, strict=True)],
            [np.concatenate([local[s], parent_offsets[out]]) for s, out in enumerate(outer)], nan)
        order = [index[skeleton.root]]  # the tree, each segment after its parent
        for s in order:
            order += [index[joints[k].child] for k in outer[s]]
        # trilateration of joint k: its distances to the markers of both segments and to the parent's own joint
        parent = [index[j.parent] for j in joints]
        child = [index[j.child] for j in joints]
        up = [inner.get(j.parent, -1) for j in joints]
        radii = [np.concatenate([
            np.linalg.norm(local[parent[k]] - parent_offsets[k], axis=1),
            np.linalg.norm(local[child[k]] - child_offsets[k], axis=1),
            [np.linalg.norm(child_offsets[up[k]] - parent_offsets[k])] if up[k] >= 0 else []])
            for k in range(len(joints))]
        padded_radii = np.full((len(joints), max((len(r) for r in radii), default=0)), np.nan)
        for k, r in enumerate(radii):
            padded_radii[k, :len(r)] = r
        self._model = (columns, marker_local, np.array(order, dtype=np.intp),
                       np.array([inner.get(n, -1) for n in self.names], dtype=np.intp), point_columns, point_local,
                       np.array(parent, dtype=np.intp), np.array(child, dtype=np.intp), parent_offsets,
                       child_offsets, np.array(up, dtype=np.intp), padded_radii,
                       np.array([len(m) for m in local], dtype=np.intp))
        self._parents = np.array(self.parents, dtype=np.intp)
        self._held = np.full((len(self.names), 4), np.nan)  # per segment: its last determined turn from its parent
        self._held_at = np.zeros(len(self.names), dtype=np.intp)  # and that frame's index before the next call's first

    def __call__(self, positions: np.ndarray, progress: Progress | None = None) -> SkeletonPose:
        """The pose in every frame of (F, N, 3) trajectories in the solver's label order (NaN gaps). ``progress``
        hears of each segment posed, in both passes, for a long recording."""
        positions = np.ascontiguousarray(positions, dtype=np.float64)
        (columns, marker_local, order, inner, point_columns, point_local, parent, child, parent_offsets,
         child_offsets, up, radii, sizes) = self._model
        sources, observed = _sources(positions, columns, marker_local, child, child_offsets)
        total = 2 * len(order) if progress is not None else 0
        held = (self._held, self._held_at)
        passes = _top_down(sources, order, inner, point_columns, point_local, parent, parent_offsets, child_offsets,
                           held, progress, 0, total)
        # a parent showing too few points of its own, whose child's markers cannot place their joint either (fewer
        # than three visible), gets that joint where its distances to every visible marker of both segments and to
        # the parent's own joint are right, and is fitted again with it
        if _trilaterate_joints(sources, observed, _centres(*passes[:2], parent, child, parent_offsets, child_offsets),
                               parent, child, up, radii, sizes, positions.shape[1] + 1):
            passes = _top_down(sources, order, inner, point_columns, point_local, parent, parent_offsets,
                               child_offsets, held, progress, len(order), total)
        matrices, translations, rotations, determined = passes
        _remember(rotations, determined, self._parents, *held)
        residual, fit = _residuals(matrices, translations, marker_local, observed)
        centres = _centres(matrices, translations, parent, child, parent_offsets, child_offsets)
        return SkeletonPose(self.names, self.joint_names, self.parents, rotations, translations, centres, residual,
                            fit)


def _top_down(sources: np.ndarray, order: np.ndarray, inner: np.ndarray, point_columns: np.ndarray,
              point_local: np.ndarray, parent: np.ndarray, parent_offsets: np.ndarray, child_offsets: np.ndarray,
              held: tuple[np.ndarray, np.ndarray], progress: Progress | None, done: int,
              total: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every segment fitted from the root down (``_fit_segments``, holding from ``held``: the solver's remembered
    turns): matrices, translations, quaternions and whether the points fixed each. One compiled call, or one
    per segment when ``progress`` is to hear of each."""
    frames, count = sources.shape[0], len(order)
    matrices, translations, rotations = (np.empty((frames, count, *shape)) for shape in ((3, 3), (3,), (4,)))
    for unposed in (matrices, translations, rotations):
        unposed.fill(np.nan)  # half the cost of np.full, which a live frame pays three times
    determined = np.zeros((frames, count), bool)
    state = (sources, inner, point_columns, point_local, parent, parent_offsets, child_offsets, matrices,
             translations, rotations, determined, *held)
    if progress is None:
        _fit_segments(order, *state)
    else:
        for k in range(count):
            _fit_segments(order[k:k + 1], *state)
            progress("solve", done + k + 1, total)
    return matrices, translations, rotations, determined


@njit(cache=True)
def _fit_segments(order: np.ndarray, sources: np.ndarray, inner: np.ndarray, point_columns: np.ndarray,
                  point_local: np.ndarray, parent: np.ndarray, parent_offsets: np.ndarray,
                  child_offsets: np.ndarray, matrices: np.ndarray, translations: np.ndarray, rotations: np.ndarray,
                  determined: np.ndarray, held: np.ndarray, held_at: np.ndarray) -> None:  # pragma: no cover
    """In place, the segments ``order`` (each after its parent) in every frame. The root, and a segment whose
    parent was not fixed by data in a frame while it has three points of its own, is fitted freely; every other
    segment turns about the joint its parent places (Schoenauer 3.8.2); frames whose points fix one direction only
    hold the turn from their parent that the frames around them give (``rigidfit.hold_turns``), those of earlier
    calls included (``held``, ``held_at``: ``_remember``), so that the parent carries them; a segment that no frame so
    far fixed turns as its parent does (the root, or where its parent has no pose: not at all from the skeleton's own
    axes), then points at its data."""
    frames, n = sources.shape[0], point_columns.shape[1]
    points = np.empty((frames, n, 3))
    origin_loc, origin_obs, reference = np.empty((frames, 3)), np.empty((frames, 3)), np.empty((frames, 4))
    pivot_local, pivot_world = np.zeros(3), np.empty(3)
    seen, x, y = np.empty(n), np.empty((n, 3)), np.empty((n, 3))
    for s in order:
        k = inner[s]
        if k >= 0:
            pivot_local[:] = child_offsets[k]
        for f in range(frames):
            own = 0
            for i, c in enumerate(point_columns[s]):
                points[f, i] = sources[f, c]
                own += finite(points[f, i])
            pivot_world[:] = np.nan
            if k >= 0 and (determined[f, parent[k]] or own < 3):
                place(matrices[f, parent[k]], parent_offsets[k], translations[f, parent[k]], pivot_world)
            determined[f, s] = fit_frame(point_local[s], points[f], pivot_local, pivot_world, MIN_GAP, seen, x, y,
                                         rotations[f, s], origin_loc[f], origin_obs[f])
        if not determined[:, s].all():  # held relative to its parent, which carries it (the root: in the world)
            for f in range(frames):
                _reference(rotations[f], -1 if k < 0 else parent[k], reference[f])
            hold_turns(rotations[:, s], determined[:, s], point_local[s], points, origin_loc, origin_obs, reference,
                       held[s], held_at[s])
        for f in range(frames):
            pose_matrix(rotations[f, s], origin_loc[f], origin_obs[f], matrices[f, s], translations[f, s])


@njit(cache=True)
def _reference(rotations: np.ndarray, parent: int, out: np.ndarray) -> None:  # pragma: no cover
    """Into ``out``: the rotation a segment's turn is held relative to in a frame of (S, 4) ``rotations``: its
    ``parent`` segment's (-1: none), or the identity where the parent has no pose."""
    if parent >= 0 and finite(rotations[parent]):
        out[:] = rotations[parent]
    else:
        out[:3], out[3] = 0.0, 1.0


@njit(cache=True)
def _remember(rotations: np.ndarray, determined: np.ndarray, parents: np.ndarray, held: np.ndarray,
              held_at: np.ndarray) -> None:  # pragma: no cover
    """In place, after a call over (F, S) frames: each segment's turn from its parent (``parents``: -1 for the root,
    whose turn is from the world) in its last frame whose points fixed it (``held``), and that frame's index counted
    from the next call's first frame (``held_at``, negative)."""
    frames = len(rotations)
    reference = np.empty(4)
    for s in range(rotations.shape[1]):
        held_at[s] -= frames
        for f in range(frames - 1, -1, -1):
            if determined[f, s]:
                _reference(rotations[f], parents[s], reference)
                relative_turn(reference, rotations[f, s], held[s])
                held_at[s] = f - frames
                break


@njit(cache=True)
def _sources(positions: np.ndarray, columns: np.ndarray, marker_local: np.ndarray, child: np.ndarray,
             child_offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """(F, N + 1 + J, 3): the positions, the NaN column, then each joint where its child's own markers alone place
    it (a free fit that fixes all three angles), NaN elsewhere; and (F, S, n, 3) each segment's markers from them
    (``columns``)."""
    frames, count, n = positions.shape[0], positions.shape[1], columns.shape[1]
    sources = np.full((frames, count + 1 + len(child), 3), np.nan)
    sources[:, :count] = positions
    observed = np.empty((frames, len(columns), n, 3))
    for f in range(frames):
        for s in range(len(columns)):
            for i in range(n):
                observed[f, s, i] = sources[f, columns[s, i]]
    pivot_local, pivot_world = np.zeros(3), np.full(3, np.nan)
    quat, origin_loc, origin_obs = np.empty(4), np.empty(3), np.empty(3)
    matrix, translation = np.empty((3, 3)), np.empty(3)
    seen, x, y = np.empty(n), np.empty((n, 3)), np.empty((n, 3))
    for k, c in enumerate(child):
        for f in range(frames):
            if fit_frame(marker_local[c], observed[f, c], pivot_local, pivot_world, MIN_GAP, seen, x, y, quat,
                         origin_loc, origin_obs):
                pose_matrix(quat, origin_loc, origin_obs, matrix, translation)
                place(matrix, child_offsets[k], translation, sources[f, count + 1 + k])
    return sources, observed


@njit(cache=True)
def _trilaterate_joints(sources: np.ndarray, observed: np.ndarray, centres: np.ndarray, parent: np.ndarray,
                        child: np.ndarray, up: np.ndarray, radii: np.ndarray, sizes: np.ndarray,
                        first: int) -> bool:  # pragma: no cover
    """In place in ``sources`` (joints from column ``first``): in frames where a joint's parent shows fewer points
    of its own than it needs (three for the root, two below it) and its child did not place it, the joint where
    its distances to the visible markers of both segments (and to the parent's own joint, from ``centres``) are
    ``radii``. Whether any joint was placed so."""
    placed = False
    space = np.empty((2 * sizes.max() + 1, 3))
    for k in range(len(parent)):
        p, c = parent[k], child[k]
        least = 2 if up[k] >= 0 else 3
        points = space[:sizes[p] + sizes[c] + (1 if up[k] >= 0 else 0)]
        for f in range(len(sources)):
            visible = 0
            for i in range(sizes[p]):
                if finite(observed[f, p, i]):
                    visible += 1
            if visible >= least or finite(sources[f, first + k]):
                continue
            points[:sizes[p]] = observed[f, p, :sizes[p]]
            points[sizes[p]:sizes[p] + sizes[c]] = observed[f, c, :sizes[c]]
            if up[k] >= 0:
                points[-1] = centres[f, up[k]]
            found = _trilaterate(points, radii[k, :len(points)], centres[f, k])
            if finite(found):
                sources[f, first + k] = found
                placed = True
    return placed


@njit(cache=True)
def _trilaterate(points: np.ndarray, radii: np.ndarray, start: np.ndarray, iterations: int = 10,
                 least: int = 4) -> np.ndarray:  # pragma: no cover
    """The point whose distances to the visible (K, 3) ``points`` are the (K,) ``radii`` (least squares, damped
    Gauss-Newton from ``start``); NaN where fewer than ``least`` points are visible or no start."""
    seen = 0
    for i in range(len(points)):
        seen += finite(points[i])
    x = start.copy()
    if seen < least or not finite(start):
        x[:] = np.nan
        return x
    normal, gradient, unit = np.empty((3, 3)), np.empty(3), np.empty(3)
    for _ in range(iterations):
        normal[:] = 1e-6 * np.eye(3)
        gradient[:] = 0.0
        for i in range(len(points)):
            if finite(points[i]):
                unit[:] = x - points[i]
                dist = max(np.sqrt(unit[0] ** 2 + unit[1] ** 2 + unit[2] ** 2), 1e-9)
                unit /= dist
                for a in range(3):
                    gradient[a] += unit[a] * (dist - radii[i])
                    for b in range(3):
                        normal[a, b] += unit[a] * unit[b]
        x -= _solve3(normal, gradient)
    return x


@njit(cache=True)
def _solve3(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # pragma: no cover
    """The solution of the 3x3 system ``a x = b`` by Cramer's rule (``a`` is well conditioned here: a sum of unit
    outer products plus a small multiple of the identity)."""
    x, m = np.empty(3), np.empty((3, 3))
    for k in range(3):
        m[:] = a
        m[:, k] = b
        x[k] = det3(m)
    return x / det3(a)


@njit(cache=True)
def _centres(matrices: np.ndarray, translations: np.ndarray, parent: np.ndarray, child: np.ndarray,
             parent_offsets: np.ndarray, child_offsets: np.ndarray) -> np.ndarray:  # pragma: no cover
    """(F, J, 3) joint centres: ``joint_track`` of every joint at once (the mean of where its two segments put it,
    or the one that knows)."""
    centres = np.full((len(matrices), len(parent), 3), np.nan)
    at, total = np.empty(3), np.empty(3)
    for f in range(len(matrices)):
        for k in range(len(parent)):
            total[:], count = 0.0, 0
            for side in range(2):
                s = parent[k] if side == 0 else child[k]
                place(matrices[f, s], parent_offsets[k] if side == 0 else child_offsets[k], translations[f, s], at)
                if finite(at):
                    total += at
                    count += 1
            if count:
                for a in range(3):
                    centres[f, k, a] = total[a] / count
    return centres


@njit(cache=True)
def _residuals(matrices: np.ndarray, translations: np.ndarray, marker_local: np.ndarray,
               observed: np.ndarray) -> tuple[np.ndarray, float]:  # pragma: no cover
    """(F, S) RMS distance between fitted and observed markers (NaN where a segment shows none), and the mean
    distance over every seen marker of a posed segment."""
    residual = np.full(observed.shape[:2], np.nan)
    diff, shift = np.empty(3), np.empty(3)
    total, count = 0.0, 0
    for f in range(observed.shape[0]):
        for s in range(observed.shape[1]):
            err, seen = 0.0, 0
            for i in range(observed.shape[2]):
                if finite(observed[f, s, i]):
                    for a in range(3):
                        shift[a] = translations[f, s, a] - observed[f, s, i, a]
                    place(matrices[f, s], marker_local[s, i], shift, diff)
                    square = diff[0] * diff[0] + diff[1] * diff[1] + diff[2] * diff[2]
                    err += square
                    seen += 1
                    if np.isfinite(square):
                        total += np.sqrt(square)
                        count += 1
            if seen:
                residual[f, s] = np.sqrt(err / seen)
    return residual, total / count if count else np.nan


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
