"""Real-time occlusion filling: a Kalman filter per marker fed by rigid-body constraints (Aristidou 2008, ch. 5).

Every marker has a constant-velocity Kalman filter (``kalman.ConstantVelocityBank``). An observed marker is its own
measurement. A missing marker on a segment gets a measurement built from what is still visible, by occlusion case
(5.3), and its filter's estimate is the output:

- two or more markers of its segment visible (code 3): with three or more anchor points the segment's pose is fitted
  to them; with two, each marker goes to the point nearest its rotated-offset estimate on the circle where the
  spheres about the two anchors meet (5.3.2, appendix C);
- one visible (code 4): the rotated offset from that marker (5.3.3);
- none visible, a neighbouring segment with visible markers (code 5): the rotated offset from their shared centre of
  rotation, placed by the neighbour (5.3.4, eq. 4.35);
- the neighbours hidden too (code 6): placed through a joint of a neighbour itself estimated, or, with no neighbour
  at all, turned on by its last rotor (constant rotor, 5.3.4);
- a marker seen by one camera only (code 7): its estimate is projected onto that camera's ray (5.3.5) before the
  other missing markers of its segment are placed, so they can lean on it (6.2.4);
- no usable segment (code 2): its filter's prediction alone.

Changes to the thesis, each backed by its results (tables 6.1-6.6) or needed for gaps of seconds:

- Offsets come from the segment model (fixed local marker positions), not from the previous frame's vectors, so the
  inter-marker distances cannot drift over a long gap.
- A centre of rotation is one more anchor point of its segment, also while one or two of its markers remain visible
  (``joint_anchors="partial"``; the thesis's use, whole segment hidden only, is ``"hidden"``). With a skeleton this
  is the largest gain: the rotation about the line through two visible markers is otherwise unknown.
- The rotation left free by fewer than three anchors is held relative to the steadiest posed neighbour (a hinge
  first, then the parent), not extrapolated in the world: a held joint angle errs far less than a constant rotor
  over seconds (``hidden_rotation``). With two anchors the hold is a swing-twist split about the anchor line taken
  when the gap starts, so the twist cannot creep as the line moves (a frame-to-frame minimal rotation accumulates
  holonomy over a walking cycle).
- A single-camera marker is also slid along its ray to match its distances to the visible markers of its segment,
  with the projected estimate as a prior (appendices D and E combined with 5.3.5: ``ray_distances``).
- Joint centres (tables 6.1, 6.2): from the side whose markers are all visible when only one is, the mean of both
  sides otherwise. Learned joint offsets (no skeleton) are updated from frames with predicted markers only while
  each side keeps a visible marker, never from a fully hidden segment (table 6.3; ``update_joint_offsets``).
- A marker predicted from its past alone (its filter, or a constant rotor with nothing visible) coasts to rest
  (``coast_decay_s``) and is given up after ``extrapolate_max_s``, rather than flying off for seconds.

The filler never reads a future frame: ``update`` uses the current frame and its own state only, so filling a
recording frame by frame (``fill_sequence``) gives exactly what a live stream would have given.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import Literal, TypeVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.linalg.lapack import dgesdd
from scipy.sparse.csgraph import minimum_spanning_tree
from scipy.spatial.transform import Rotation

from mocapflow.mocap.clustering import SegmentTracker, segment_names
from mocapflow.mocap.cor import RigidFit, SequentialCoR
from mocapflow.mocap.kalman import ConstantVelocityBank
from mocapflow.mocap.model import Joint, Segment, SkeletonModel


class FillCase(IntEnum):
    """Per-marker flag of a filled frame: how its position was obtained."""

    MISSING = 0  # unfillable, left NaN
    OBSERVED = 1
    KALMAN = 2  # the marker's own filter only
    ONE_MISSING = 3  # two or more markers of the segment visible (rigid fit, or the two-sphere circle)
    TWO_MISSING = 4  # one marker of the segment visible (rotated offset)
    VIA_JOINT = 5  # whole segment hidden, placed through the neighbour's centre of rotation
    CONSTANT_ROTOR = 6  # segment and neighbours hidden: through an estimated neighbour's joint, else constant rotor
    RAY = 7  # seen by a single camera: on its ray


_T = TypeVar("_T")
_PATTERNS_KEPT = 64  # visibility patterns whose index work is kept (``_recall``)
_MISSING, _OBSERVED, _KALMAN = int(FillCase.MISSING), int(FillCase.OBSERVED), int(FillCase.KALMAN)
_ONE_MISSING = int(FillCase.ONE_MISSING)


class FillerConfig(BaseModel):
    """Noise levels, constraint choices and online-learning settings of the filler."""

    model_config = ConfigDict(extra="forbid")

    accel_sd: float = Field(
        50000.0, gt=0, description="white-noise acceleration of the constant-velocity model (mm/s^2)")
    initial_speed_sd: float = Field(1000.0, gt=0, description="spread of a new marker's unknown speed (mm/s)")
    observed_sd: float = Field(0.5, gt=0, description="measurement noise of an observed marker (mm)")
    rigid_sd: float = Field(0.5, gt=0, description="noise of an estimate from two or more visible markers (mm)")
    offset_sd: float = Field(1.0, gt=0, description="noise of an estimate from one visible marker (mm)")
    joint_sd: float = Field(1.0, gt=0, description="noise of an estimate through a centre of rotation (mm)")
    rotor_sd: float = Field(5.0, gt=0, description="noise of a constant-rotor estimate (mm)")
    ray_sd: float = Field(2.0, gt=0, description="noise of an estimate projected on a camera ray (mm)")
    ray_distances: bool = Field(
        True, description="move a single-camera marker along its ray to match its distances to the visible markers "
        "of its segment (appendices D, E), not only project the estimate on the ray (5.3.5)")
    joint_anchors: Literal["hidden", "partial"] = Field(
        "partial", description="use a neighbour's centre of rotation only when the whole segment is hidden, or also "
        "when one or two of its markers remain visible")
    joint_weight: float = Field(0.5, gt=0, description="weight of a centre of rotation against a marker in a fit")
    hidden_rotation: Literal["joint", "rotor"] = Field(
        "joint", description="rotation of a segment placed through a single anchor: keep its rotation relative to "
        "the posed neighbour (joint angles held), or turn on by its last rotor in the world (the thesis's constant "
        "rotor)")
    coast_decay_s: float | None = Field(
        0.25, gt=0, description="time constant (s) of the velocity decay of a marker tracked by its filter alone")
    extrapolate_max_s: float | None = Field(
        0.5, gt=0, description="give up a marker predicted from its past alone (its own filter, or a constant rotor "
        "with nothing visible to anchor its segment) after this long (s); none: never")
    learn: bool = Field(True, description="learn whatever the skeleton does not give (segments, marker offsets, "
                        "joints) from the frames seen so far")
    cluster_method: Literal["spectral", "distance-threshold"] = Field(
        "spectral", description="how markers are grouped into segments when no skeleton gives them")
    rigid_tolerance: float = Field(
        5.0, gt=0, description="largest SD of a within-segment marker distance, for distance-threshold grouping (mm)")
    learn_stride: int = Field(4, ge=1, description="frames between two samples of marker distances and poses")
    learn_window_s: float = Field(20.0, gt=0, description="seconds of samples behind the grouping")
    learn_warmup_s: float = Field(2.0, gt=0, description="seconds of samples before the first grouping")
    regroup_s: float = Field(2.0, gt=0, description="seconds between updates of the learned model (the grouping "
                             "is checked up to four times less often while it holds)")
    min_joint_rotation_deg: float = Field(
        5.0, gt=0, description="least RMS relative rotation of two segments before a joint between them is trusted")
    min_joint_s: float = Field(2.0, gt=0, description="seconds of usable frames before a learned joint is trusted")
    outlier_mm: float = Field(
        1000.0, gt=0, description="a sample this far from where its marker, seen in the previous frame, is predicted "
        "is an outlier (a reflection, a glitch) and treated as missing, not trusted")
    update_joint_offsets: Literal["observed", "partial", "always"] = Field(
        "partial", description="frames that update learned joint offsets: both sides fully observed; also with "
        "predicted markers while each side keeps one visible (tables 6.1-6.3); or every frame")


class FillResult:
    """One filled frame: ``positions`` (N, 3), NaN only where unfillable; ``flags`` (N,) uint8 ``FillCase`` codes;
    ``joint_centres`` (J, 3) when joints are known (rows named by ``GapFiller.joint_names``), else None.

    Joint centres are computed when first read, so a caller that never reads them does not pay for them.
    """

    __slots__ = ("_centres", "flags", "positions")

    def __init__(self, positions: np.ndarray, flags: np.ndarray,
                 joint_centres: np.ndarray | Callable[[], np.ndarray] | None) -> None:
        self.positions = positions
        self.flags = flags
        self._centres = joint_centres

    @property
    def joint_centres(self) -> np.ndarray | None:
        if callable(self._centres):
            self._centres = self._centres()
        return self._centres


def _fit_one(local: np.ndarray, world: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
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


def nearest_on_circle(
    p1: np.ndarray, p2: np.ndarray, r1: np.ndarray, r2: np.ndarray, guess: np.ndarray
) -> np.ndarray:
    """Points on the circles where spheres (p1, r1) and (p2, r2) meet, nearest to ``guess`` (appendix C).

    All arguments are batched (K, 3) or (K,). Spheres that miss each other (noise) give their closest point on the
    line of centres; a guess on the axis keeps its direction from the closest circle point to it.
    """
    axis = p2 - p1
    d = np.maximum(np.linalg.norm(axis, axis=-1), 1e-9)
    u = axis / d[:, None]
    along = (d**2 + r1**2 - r2**2) / (2 * d)
    radius = np.sqrt(np.maximum(r1**2 - along**2, 0.0))
    centre = p1 + along[:, None] * u
    v = guess - centre
    v -= np.einsum("ki,ki->k", v, u)[:, None] * u
    norm = np.linalg.norm(v, axis=-1)
    v /= np.maximum(norm, 1e-300)[:, None]
    on_axis = ~(norm > 1e-9)
    if on_axis.any():
        fallback = np.cross(u[on_axis], np.where(np.abs(u[on_axis, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
        v[on_axis] = fallback / np.linalg.norm(fallback, axis=-1, keepdims=True)
    return centre + radius[:, None] * v


def _unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), 1e-12)


def _swing(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``u`` to unit vector ``v``, from the half-way quaternion (always
    orthonormal; written out because it runs per hidden segment and frame)."""
    ux, uy, uz = u.tolist()
    vx, vy, vz = v.tolist()
    w, x, y, z = 1.0 + ux * vx + uy * vy + uz * vz, uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
    if w < 1e-9:  # opposite: half a turn about a perpendicular
        w, (x, y, z) = 0.0, np.cross(u, [1.0, 0, 0] if abs(ux) < 0.9 else [0, 1.0, 0]).tolist()
    n = w * w + x * x + y * y + z * z
    s = 2.0 / n
    return np.array([
        [1 - s * (y * y + z * z), s * (x * y - w * z), s * (x * z + w * y)],
        [s * (x * y + w * z), 1 - s * (x * x + z * z), s * (y * z - w * x)],
        [s * (x * z - w * y), s * (y * z + w * x), 1 - s * (x * x + y * y)]])


def project_on_rays(points: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Orthogonal projections of ``points`` (K, 3) on the lines ``rays`` (K, 6) = origin + direction (5.3.5)."""
    origin, direction = rays[:, :3], rays[:, 3:]
    direction = direction / np.linalg.norm(direction, axis=-1, keepdims=True)
    return origin + np.einsum("ki,ki->k", points - origin, direction)[:, None] * direction


@dataclass
class _Joint:
    parent: int
    child: int
    parent_offset: np.ndarray  # (3,) in the parent's local frame
    child_offset: np.ndarray  # (3,) in the child's local frame


class _Body:
    """A skeleton compiled against the filler's label order, padded for batched per-segment work.

    The index work that depends only on which markers are visible (segments near the gaps, pose-fit weights,
    per-segment selections) is kept per visibility pattern (``_recall``): a gap keeps its pattern for many frames.
    """

    def __init__(self, skeleton: SkeletonModel, labels: list[str]) -> None:
        index = {label: i for i, label in enumerate(labels)}
        n = len(labels)
        self.names: list[str] = []
        self.members: list[np.ndarray] = []
        self.offsets: list[np.ndarray] = []
        for seg in skeleton.segments:
            keep = [k for k, m in enumerate(seg.markers) if m in index]
            if len(keep) < 2 or seg.marker_offsets is None:
                continue  # a lone marker or an unknown shape constrains nothing
            self.names.append(seg.name)
            self.members.append(np.array([index[seg.markers[k]] for k in keep]))
            self.offsets.append(np.array([seg.marker_offsets[k] for k in keep], dtype=float))
        s = len(self.members)
        width = max((len(m) for m in self.members), default=0)
        self.idx = np.full((s, width), n)  # padding points at a NaN row appended to positions
        self.local = np.zeros((s, width, 3))
        self.slot = np.zeros((s, width), dtype=bool)
        self.marker_seg = np.full(n, -1)
        self.marker_local = np.zeros((n, 3))  # per marker: its offset in its segment
        for k, (members, offsets) in enumerate(zip(self.members, self.offsets, strict=True)):
            self.idx[k, : len(members)] = members
            self.local[k, : len(members)] = offsets
            self.slot[k, : len(members)] = True
            self.marker_seg[members] = k
            self.marker_local[members] = offsets
        seg_index = {name: k for k, name in enumerate(self.names)}
        self.joint_names: list[str] = []
        self.joints: list[_Joint | None] = []  # None: a joint of the skeleton this body cannot use
        self.neighbours: list[list[tuple[int, int]]] = [[] for _ in range(s)]  # (joint, other segment)
        for j in skeleton.joints:
            self.joint_names.append(j.name)
            p, c = seg_index.get(j.parent), seg_index.get(j.child)
            if p is None or c is None or j.parent_offset is None or j.child_offset is None:
                self.joints.append(None)
                continue
            self.joints.append(_Joint(p, c, np.array(j.parent_offset, float), np.array(j.child_offset, float)))
            self.neighbours[p].append((len(self.joints) - 1, c))
            self.neighbours[c].append((len(self.joints) - 1, p))
        kinds = [j.kind for j in skeleton.joints]
        for k, links in enumerate(self.neighbours):  # the steadiest reference first: a hinge, then the parent
            links.sort(key=lambda link: (kinds[link[0]] != "hinge", self.joints[link[0]].child != k))
        # per segment: (joint, neighbour, centre in this segment's frame, centre in the neighbour's frame)
        self.links = [[(j, other, self.joint_offset(j, k), self.joint_offset(j, other)) for j, other in links]
                      for k, links in enumerate(self.neighbours)]
        self.in_segment = self.marker_seg >= 0
        self.near = np.zeros((n, s), dtype=bool)  # per marker: its segment and that segment's neighbours
        for m, k in enumerate(self.marker_seg):
            if k >= 0:
                self.near[m, [k, *(other for _, other in self.neighbours[k])]] = True
        usable = [j for j in self.joints if j is not None]
        self.joint_usable = np.array([j is not None for j in self.joints], dtype=bool)
        self.joint_segments = np.array([[j.parent, j.child] for j in usable], dtype=int).reshape(-1, 2)
        self.joint_offsets = np.array([[j.parent_offset, j.child_offset] for j in usable]).reshape(-1, 2, 3)
        self._around: dict[bytes, np.ndarray] = {}  # by visibility pattern
        self._fits: dict[bytes, _Fit] = {}
        self._layouts: dict[bytes, _Layout] = {}

    def joint_offset(self, joint: int, segment: int) -> np.ndarray:
        """The centre of ``joint`` in ``segment``'s local frame."""
        jt = self.joints[joint]
        assert jt is not None
        return jt.parent_offset if jt.parent == segment else jt.child_offset

    def fit_for(self, use: np.ndarray, segments: np.ndarray) -> _Fit:
        """The ``_Fit`` of ``segments`` to the markers selected by ``use`` (N,) bool."""
        return _recall(self._fits, use.tobytes() + segments.tobytes(), lambda: _Fit(self, use, segments))

    def layout(self, visible: np.ndarray, targets: np.ndarray, near: np.ndarray) -> _Layout:
        """The ``_Layout`` of a visibility pattern."""
        return _recall(self._layouts, visible.tobytes() + targets.tobytes() + near.tobytes(),
                       lambda: _Layout(self, visible, targets, near))

    def around(self, markers: np.ndarray) -> np.ndarray:
        """Indices of the segments holding any of ``markers`` (N,) bool, and of their neighbours."""
        return _recall(self._around, markers.tobytes(), lambda: np.flatnonzero(self.near[markers].any(axis=0)))


def _recall(cache: dict[bytes, _T], key: bytes, make: Callable[[], _T]) -> _T:
    """``cache[key]``, made by ``make`` when missing. The keys are visibility patterns (the bytes of boolean masks);
    patterns that do not repeat (scattered dropouts) are dropped by emptying the cache when it is full."""
    value = cache.get(key)
    if value is None:
        if len(cache) >= _PATTERNS_KEPT:
            cache.clear()
        value = cache[key] = make()
    return value


class _Fit:
    """The pose fit of some segments to the markers of one visibility pattern: what depends on the pattern alone is
    worked out once (``cor.RigidFit``). ``complete``: the segments with all their markers in the pattern."""

    def __init__(self, body: _Body, use: np.ndarray, segments: np.ndarray) -> None:
        idx = body.idx[segments]
        used = np.append(use, False)[idx]
        self.rows = np.minimum(idx, len(use) - 1)  # (B, M) marker rows, padding on any real row (unused)
        self.used = used[..., None]
        self.rigid = RigidFit(body.local[segments], used.astype(float))
        self.complete = (used | ~body.slot[segments]).all(axis=1)

    def __call__(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """R (B, 3, 3), t (B, 3) and ``ok`` (B,) of the segments fitted to ``positions`` (N, 3); ``ok`` is False where
        the pattern's markers do not fix the pose."""
        return self.rigid(np.where(self.used, positions[self.rows], 0.0))


class _Layout:
    """The index work of ``GapFiller._constrain`` for one visibility pattern (``visible`` markers, ``targets`` to
    estimate, segments ``near`` them).

    ``seg_vis``: visible markers per segment; ``target_rows``, ``target_seg``, ``target_local``: each target's row,
    segment and offset in it; ``segments``: the segments holding a target; ``fit``: the pose fit of the ``near``
    segments; ``parts``: per segment holding a target, the rows, offsets and anchor names of its visible markers,
    the rows of its targets and which of its markers they are.
    """

    def __init__(self, body: _Body, visible: np.ndarray, targets: np.ndarray, near: np.ndarray) -> None:
        self.seg_vis = np.bincount(body.marker_seg[visible & body.in_segment], minlength=len(body.members))
        self.target_rows = np.flatnonzero(targets & body.in_segment)
        self.target_seg = body.marker_seg[self.target_rows]
        self.target_local = body.marker_local[self.target_rows]
        self.segments = np.unique(self.target_seg)
        self.fit = body.fit_for(visible, near)
        self.parts: dict[int, tuple[np.ndarray, np.ndarray, list[tuple[str, int]], np.ndarray, np.ndarray]] = {}
        for k in self.segments.tolist():
            members = body.members[k]
            vis, hit = visible[members], targets[members]
            self.parts[k] = (members[vis], body.offsets[k][vis], [("marker", x) for x in members[vis].tolist()],
                             members[hit], hit)


def is_complete(skeleton: SkeletonModel) -> bool:
    """True when every segment has marker offsets and every joint both offsets: nothing is left to learn."""
    return all(seg.marker_offsets is not None for seg in skeleton.segments) and all(
        j.parent_offset is not None and j.child_offset is not None for j in skeleton.joints)


class _Learner:
    """The body model learned online from the frames seen so far, for whatever a given skeleton leaves open.

    - Segments: markers whose mutual distances keep a small spread (``clustering.SegmentTracker`` on a sample of the
      frames), unless the skeleton gives them.
    - Marker offsets: the segment's markers in the first frame showing three of them (both of a pair), centred on
      their centroid (the reference frame of Aristidou 4.4); a marker not seen then is added when first seen with
      three known ones. Unless given.
    - Joints: for every two segments, the closed-form centre of rotation (``cor.SequentialCoR``, Aristidou 4.4) fed
      with the poses of the frames allowed by ``update_joint_offsets``; the joints kept are the minimum spanning
      forest of the fit residuals among the pairs that turned enough relative to each other. A skeleton's own joints
      keep their pairs and, when given, their offsets.
    """

    def __init__(self, labels: list[str], rate: float, config: FillerConfig, given: SkeletonModel | None) -> None:
        self.labels = labels
        self.config = config
        self.tick = max(1, round(config.regroup_s * rate))
        self.min_frames = round(config.min_joint_s * rate / config.learn_stride)  # sampled frames
        self.min_spread = np.radians(config.min_joint_rotation_deg)
        index = {label: i for i, label in enumerate(labels)}
        self.tracker: SegmentTracker | None = None
        self.groups: list[tuple[int, ...]] = []
        self.names: dict[tuple[int, ...], str] = {}
        self.offsets: dict[tuple[int, ...], np.ndarray] = {}
        self.given_joints: list[Joint] | None = None
        if given is not None and given.segments:
            for seg in given.segments:
                group = tuple(index[m] for m in seg.markers if m in index)
                if not group:
                    continue
                self.groups.append(group)
                self.names[group] = seg.name
                if seg.marker_offsets is not None:
                    keep = [k for k, m in enumerate(seg.markers) if m in index]
                    self.offsets[group] = np.array([seg.marker_offsets[k] for k in keep], dtype=float)
            self.given_joints = list(given.joints) if given.joints else None
        else:
            stride = config.learn_stride
            options = {"threshold_mm": config.rigid_tolerance} if config.cluster_method == "distance-threshold" else {}
            self.tracker = SegmentTracker(
                labels, window=max(2, round(config.learn_window_s * rate / stride)),
                warmup=max(1, round(config.learn_warmup_s * rate / stride)),
                every=max(1, round(config.regroup_s * rate / stride)), method=config.cluster_method, **options)
        self.growing = {g for g in self.groups if len(g) >= 2 and g not in self.offsets}  # shapes still incomplete
        self.cors: dict[tuple[tuple[int, ...], tuple[int, ...]], SequentialCoR] = {}
        self.poses: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # per sample: R, t, usable; body order
        self.batches: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # the samples of each tick, stacked
        self.fed: dict[tuple[int, int], int] = {}  # per segment pair: batches already fed to its estimator
        self.queue: list[tuple[int, int]] = []  # pairs still to update in this round, a few per frame
        self.per_frame = 1
        self.found: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, float]] = {}
        self.body_groups: list[tuple[int, ...]] = []
        self.joints: list[Joint] = [j for j in self.given_joints or [] if j.parent_offset is not None
                                    and j.child_offset is not None]
        self.frame = 0

    def observe(self, observed: np.ndarray, seen: np.ndarray, flags: np.ndarray, body: _Body | None,
                poses: Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray]]) -> SkeletonModel | None:
        """Take one frame (observed positions, the filled frame's flags, and a way to get the body's poses, read on
        sampled frames only); returns a new model when the learned one changed."""
        self.frame += 1
        changed = False
        if self.tracker is not None and self.frame % self.config.learn_stride == 0:
            segments = self.tracker.update(np.where(seen[:, None], observed, np.nan))
            if segments is not None:
                index = {label: i for i, label in enumerate(self.labels)}
                groups = [tuple(index[m] for m in seg.markers) for seg in segments.segments]
                names = segment_names(groups, self.labels)
                self.groups = groups
                self.names = dict(zip(groups, names, strict=True))
                self.offsets = {g: o for g, o in self.offsets.items() if g in self.names}
                self.growing = {g for g in groups if len(g) >= 2 and not np.isfinite(self.offsets.get(g, np.nan)).all()}
                self.cors = {k: c for k, c in self.cors.items() if k[0] in self.names and k[1] in self.names}
                changed = True
        for group in [g for g in self.growing if self._learn_offsets(g, observed, seen)]:
            changed = True
            if np.isfinite(self.offsets[group]).all():
                self.growing.remove(group)
        if body is not None and self.body_groups and self.frame % self.config.learn_stride == 0:
            r, t, known = poses()
            self.poses.append((r, t, known & self._usable(body, flags)))
        if changed:  # samples and pairs are in the old body's segment order
            self.poses.clear()
            self.batches.clear()
            self.fed.clear()
            self.queue.clear()
            return self._model()
        if self.frame % self.tick == 0 and self.poses:
            self.batches.append(tuple(np.stack(x) for x in zip(*self.poses, strict=True)))  # type: ignore[arg-type]
            self.poses.clear()
            if not self.queue:
                self.queue, self.found = self._pairs(), {}
                self.per_frame = max(1, -(-2 * len(self.queue) // self.tick))  # a round within half a tick
        if self.queue:  # spread over frames, so no single frame pays for every pair
            for pair in self.queue[: self.per_frame]:
                self._update_pair(*pair)
            del self.queue[: self.per_frame]
            if not self.queue:
                done = min(self.fed.values(), default=0)
                self.batches = self.batches[done:]
                self.fed = {pair: n - done for pair, n in self.fed.items()}
                joints = self._select_joints()
                if joints != self.joints:
                    self.joints = joints
                    return self._model()
        return None

    def _learn_offsets(self, group: tuple[int, ...], observed: np.ndarray, seen: np.ndarray) -> bool:
        """Start a segment's shape from the first frame showing three of its markers (both of a pair), centred on
        their centroid, and add each other marker when first seen with three known ones; True when it grew."""
        members = np.array(group)
        vis = seen[members]
        offsets = self.offsets.get(group)
        if offsets is None:
            if vis.sum() < min(3, len(group)):
                return False
            offsets = np.full((len(group), 3), np.nan)
            offsets[vis] = observed[members[vis]] - observed[members[vis]].mean(axis=0)
            self.offsets[group] = offsets
            return True
        known = np.isfinite(offsets[:, 0])
        new = vis & ~known
        if not new.any() or (vis & known).sum() < 3:
            return False
        use = vis & known
        fit = _fit_one(offsets[use], observed[members[use]], np.ones(int(use.sum())))
        if fit is None:
            return False
        offsets[new] = (observed[members[new]] - fit[1]) @ fit[0]  # R^T (x - t)
        return True

    def _usable(self, body: _Body, flags: np.ndarray) -> np.ndarray:
        """Segments whose pose this frame may update joint offsets (``update_joint_offsets``, tables 6.1-6.3)."""
        rule = self.config.update_joint_offsets
        observed = np.append(flags == _OBSERVED, False)[body.idx]
        if rule == "observed":
            return (observed | ~body.slot).all(axis=1)
        if rule == "partial":
            return observed.any(axis=1)
        return np.ones(len(body.members), dtype=bool)

    def _pairs(self) -> list[tuple[int, int]]:
        """Segment pairs (body order) whose centre of rotation is estimated: the skeleton's joints still without
        offsets, or, with no joints given, every two segments with three or more markers."""
        groups = self.body_groups
        if self.given_joints is not None:
            by_name = {self.names[g]: k for k, g in enumerate(groups)}
            return [(by_name[j.parent], by_name[j.child]) for j in self.given_joints if j.parent in by_name
                    and j.child in by_name and (j.parent_offset is None or j.child_offset is None)]
        return [(a, b) for a in range(len(groups)) for b in range(a + 1, len(groups))
                if len(groups[a]) >= 3 and len(groups[b]) >= 3]

    def _update_pair(self, a: int, b: int) -> None:
        """Feed a pair's estimator the batches it has not seen; keep its centre if it is trustworthy yet."""
        cor = self.cors.setdefault((self.body_groups[a], self.body_groups[b]), SequentialCoR())
        for r, t, usable in self.batches[self.fed.get((a, b), 0):]:
            use = usable[:, a] & usable[:, b]
            if use.any():
                cor.update(r[use, a], t[use, a], r[use, b], t[use, b])
        self.fed[a, b] = len(self.batches)
        if cor.m < self.min_frames:
            return
        spread = np.linalg.eigvalsh(cor.m * np.eye(3) - cor.s.T @ cor.s / cor.m)[-1] / cor.m
        if spread < self.min_spread**2:
            return  # they turned too little relative to each other: any point fits
        est = cor.estimate()
        self.found[a, b] = (est.parent_offset, est.child_offset, est.residual)

    def _select_joints(self) -> list[Joint]:
        """The joints of this round: the given pairs, or the minimum spanning forest of the fit residuals."""
        groups = self.body_groups
        found = self.found
        if self.given_joints is None:
            costs = np.zeros((len(groups), len(groups)))
            for (a, b), (_, _, residual) in found.items():
                costs[a, b] = residual + 1e-9  # csgraph reads 0 as no edge
            tree = minimum_spanning_tree(costs).tocoo()
            kept = {(int(a), int(b)) for a, b in zip(tree.row, tree.col, strict=True)}
            found = {pair: estimate for pair, estimate in found.items() if pair in kept}
        given = {(j.parent, j.child): j for j in self.given_joints or []}
        joints = [j for j in self.given_joints or [] if j.parent_offset is not None and j.child_offset is not None]
        for (a, b), (pa, ch, _) in sorted(found.items()):
            parent, child = self.names[groups[a]], self.names[groups[b]]
            known = given.get((parent, child))
            joints.append(Joint(name=known.name if known else f"{parent}-{child}", parent=parent, child=child,
                                kind=known.kind if known else "ball", parent_offset=_vector(pa),
                                child_offset=_vector(ch)))
        return joints

    def _model(self) -> SkeletonModel:
        """The current model: segments with known offsets, and the joints found so far."""
        known = {g: np.isfinite(self.offsets[g][:, 0]) for g in self.groups if g in self.offsets}
        ready = [g for g in self.groups if g in known and known[g].sum() >= 2]
        self.body_groups = ready
        segments = [Segment(name=self.names[g], markers=[self.labels[m] for m, k in zip(g, known[g], strict=True) if k],
                            marker_offsets=[_vector(o) for o in self.offsets[g][known[g]]]) for g in ready]
        names = {seg.name for seg in segments}
        joints = [j for j in self.joints if j.parent in names and j.child in names]
        return SkeletonModel(name="learned", segments=segments, joints=joints,
                             root=segments[0].name if segments else "")


def _vector(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


class GapFiller:
    """Streaming occlusion filler: one ``update`` per frame returns the frame with its gaps filled.

    Markers are given in a fixed label order. With a skeleton (segments with marker offsets, joints with offsets)
    every constraint case is available at once; without one, segments, their shapes and their joints are learned from
    the frames seen so far (``FillerConfig.learn``).
    """

    def __init__(
        self, labels: list[str], rate: float, config: FillerConfig | None = None, skeleton: SkeletonModel | None = None
    ) -> None:
        if rate <= 0:
            raise ValueError(f"rate must be positive, got {rate}")
        self.labels = list(labels)
        self.rate = float(rate)
        self.config = config or FillerConfig()
        n = len(self.labels)
        cfg = self.config
        dt = 1.0 / self.rate
        self.kf = ConstantVelocityBank(n, dt, cfg.accel_sd, cfg.initial_speed_sd)
        self._coast_gain = np.exp(-dt / cfg.coast_decay_s) if cfg.coast_decay_s else 1.0
        self._max_coast = round(cfg.extrapolate_max_s * self.rate) if cfg.extrapolate_max_s else None
        self._variance = np.array([1.0, cfg.observed_sd, 1.0, cfg.rigid_sd, cfg.offset_sd, cfg.joint_sd,
                                   cfg.rotor_sd, cfg.ray_sd]) ** 2  # per FillCase; unused where nothing is measured
        self._unmeasured = np.zeros(n, dtype=np.int64)  # frames since a marker was last seen or anchored
        self._extrapolated = np.zeros(n, dtype=bool)  # this frame: predicted from its past alone (a constant rotor
        # with no anchor, or its filter along its ray)
        self._last = np.full((2, n, 3), np.nan)  # the last two filled frames, newest first
        self.body: _Body | None = None
        self._model: SkeletonModel | None = None
        self._pose_r = np.zeros((2, 0, 3, 3))
        self._pose_t = np.zeros((2, 0, 3))
        self._pose_ok = np.zeros((2, 0), dtype=bool)
        self._pose_fresh = np.zeros((2, 0), dtype=bool)  # per segment: pose this frame / last frame known
        self._learner: _Learner | None = None
        self._pending: SkeletonModel | None = None  # learned, taken up at the next frame
        self._holds: dict[int, tuple[tuple[int, tuple[str, int], tuple[str, int]], np.ndarray, np.ndarray]] = {}
        self._held: set[int] = set()  # segments whose hold was used this frame
        if skeleton is not None:
            self.set_skeleton(skeleton)
        elif cfg.learn:
            self._learner = _Learner(self.labels, self.rate, cfg, None)

    # -- model -------------------------------------------------------------------------------------------------
    def set_skeleton(self, skeleton: SkeletonModel) -> None:
        """Adopt a new body model mid-stream. What it leaves open (segments without marker offsets, joints without
        offsets) is learned from then on when ``config.learn``; poses restart from the last two filled frames."""
        complete = is_complete(skeleton)
        self._learner = None if complete or not self.config.learn else _Learner(
            self.labels, self.rate, self.config, skeleton)
        self._pending = None
        self._adopt(skeleton)

    @property
    def skeleton(self) -> SkeletonModel | None:
        """The body model in use (given, or learned so far)."""
        return self._model

    @property
    def joint_names(self) -> list[str]:
        """Names of the rows of ``FillResult.joint_centres``, which change as joints are learned."""
        return list(self.body.joint_names) if self.body is not None else []

    def _adopt(self, skeleton: SkeletonModel) -> None:
        self._model = skeleton
        self._holds = {}
        self.body = _Body(skeleton, self.labels)
        s = len(self.body.members)
        self._pose_r = np.zeros((2, s, 3, 3))
        self._pose_t = np.zeros((2, s, 3))
        self._pose_ok = np.zeros((2, s), dtype=bool)
        self._pose_fresh = np.zeros((2, s), dtype=bool)  # fitted from the last two filled frames when next needed

    @staticmethod
    def _fitted_poses_for(body: _Body, filled: np.ndarray, segments: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The poses of ``segments`` fitted to a filled frame; a segment counts as posed only with all its markers."""
        fit = body.fit_for(np.isfinite(filled).all(axis=1), segments)
        r, t, ok = fit(filled)
        return r, t, ok & fit.complete

    def _ensure_poses(self, segments: np.ndarray | slice = slice(None), ages: int = 2) -> None:
        """Fit the poses of ``segments`` (default all) in the last ``ages`` frames (this one, then the one before)
        where they were skipped (segments with every marker seen, which no gap needed)."""
        assert self.body is not None
        if self._pose_fresh[:ages, segments].all():
            return
        for age in range(ages):
            stale = np.arange(len(self.body.members))[segments]
            stale = stale[~self._pose_fresh[age, stale]]
            if len(stale):
                self._pose_r[age, stale], self._pose_t[age, stale], self._pose_ok[age, stale] = (
                    self._fitted_poses_for(self.body, self._last[age], stale))
                self._pose_fresh[age, stale] = True

    # -- per frame ---------------------------------------------------------------------------------------------
    def predict_next(self) -> np.ndarray:
        """(N, 3) where each marker is expected in the next frame: its filter's prediction, as the next ``update``
        will start from it (NaN for a marker never seen)."""
        return self.kf.predicted_position(self._velocity_gain())

    def _velocity_gain(self) -> np.ndarray | None:
        """Per-marker velocity factor of the next prediction: markers without news coast to rest."""
        coasting = self._unmeasured > 0
        return np.where(coasting, self._coast_gain, 1.0) if coasting.any() else None

    def update(self, positions: np.ndarray, rays: np.ndarray | None = None) -> FillResult:
        """Fill one frame. ``positions`` (N, 3) in label order, NaN where missing; ``rays`` (N, 6) optional origin
        and direction of the single camera ray of a marker seen by one camera (NaN rows otherwise)."""
        n = len(self.labels)
        z = np.array(positions, dtype=float).reshape(n, 3)
        seen = np.isfinite(z).all(axis=1)
        z[~seen] = np.nan
        if self._pending is not None:
            self._adopt(self._pending)
            self._pending = None
        self._extrapolated[:] = False
        self.kf.predict(self._velocity_gain())
        seen &= ~self._outliers(z, seen)
        z[~seen] = np.nan
        body = self.body
        flags = seen.astype(np.uint8)
        poses = None if seen.all() else self._fill_missing(z, seen, flags, rays)
        measured = flags >= _OBSERVED
        measured &= flags != _KALMAN
        self.kf.update(z, self._variance[flags], measured)
        estimated = flags >= _ONE_MISSING
        z[estimated] = self.kf.position[estimated]
        self._unmeasured = np.where(measured & ~self._extrapolated, 0, self._unmeasured + 1)

        self._last[1] = self._last[0]
        self._last[0] = z
        centres: np.ndarray | Callable[[], np.ndarray] | None = None
        if body is not None:
            self._pose_r[1], self._pose_t[1], self._pose_ok[1] = self._pose_r[0], self._pose_t[0], self._pose_ok[0]
            self._pose_fresh[1] = self._pose_fresh[0]
            if poses is None:  # no segment lost a marker: the fit waits until a gap or a reader needs it
                self._pose_fresh[0] = False
                self._holds.clear()  # a later gap starts its own holds
            else:  # the constraint's own poses around the gaps, so estimates cannot creep through the filter's lag
                self._pose_r[0], self._pose_t[0], self._pose_ok[0], self._pose_fresh[0] = poses
            centres = self._centres_later(z, flags)
        if self._learner is not None:  # a new model is taken up from the next frame, so the result and
            # ``joint_names`` keep describing the same body until then
            self._pending = self._learner.observe(z, seen, flags, body, self._current_poses) or self._pending
        return FillResult(positions=z, flags=flags, joint_centres=centres)

    def _outliers(self, z: np.ndarray, seen: np.ndarray) -> np.ndarray:
        """Samples of markers seen in the previous frame that are ``outlier_mm`` or more from their prediction: no
        marker moves so in one frame, so they would only pull the filter and the segment fits off."""
        followed = seen & (self._unmeasured == 0) & np.isfinite(self.kf.position).all(axis=1)
        far = np.zeros(len(z), bool)
        far[followed] = np.linalg.norm(z[followed] - self.kf.position[followed], axis=1) >= self.config.outlier_mm
        return far

    def _current_poses(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """This frame's segment poses, fitted now where skipped."""
        self._ensure_poses(ages=1)
        return self._pose_r[0].copy(), self._pose_t[0].copy(), self._pose_ok[0].copy()

    def _centres_later(self, z: np.ndarray, flags: np.ndarray) -> Callable[[], np.ndarray]:
        """The joint centres of this frame, computed on first read from its poses (fitted then where skipped)."""
        body = self.body
        assert body is not None
        flags = flags.copy()  # the caller may edit the result's arrays before reading the centres
        r, t, ok = self._pose_r[0].copy(), self._pose_t[0].copy(), self._pose_ok[0].copy()
        stale = np.flatnonzero(~self._pose_fresh[0])
        if not len(stale):
            return lambda: joint_centres(body, (r, t, ok), flags)
        z = z.copy()

        def centres() -> np.ndarray:
            r[stale], t[stale], ok[stale] = self._fitted_poses_for(body, z, stale)
            return joint_centres(body, (r, t, ok), flags)
        return centres

    def _fill_missing(
        self, z: np.ndarray, seen: np.ndarray, flags: np.ndarray, rays: np.ndarray | None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """Write measurements for the missing rows of ``z`` and their ``flags``: single-camera markers first
        (6.2.4), then the rigid-body cases, then each filter alone. Returns the segments' poses this frame (R, t,
        known, and which segments these were worked out for: those that lost a marker and their neighbours) when a
        marker of a segment was missing, else None."""
        n = len(self.labels)
        prior = self.kf.position
        body = self.body if self.body is not None and (~seen & self.body.in_segment).any() else None
        near = np.zeros(0, dtype=int)
        if body is not None:
            near = body.around(~seen)
            self._ensure_poses(near)
        visible = seen.copy()
        if rays is not None:
            rays = np.asarray(rays, dtype=float).reshape(n, 6)
            ray_rows = ~seen & np.isfinite(rays).all(axis=1) & (np.linalg.norm(rays[:, 3:], axis=1) > 0)
            if ray_rows.any():
                guess = prior.copy()
                anchored = np.zeros(n, dtype=bool)
                if body is not None:
                    est, _, _ = self._constrain(z, visible, prior, ray_rows & body.in_segment, near, keep=False)
                    anchored = np.isfinite(est).all(axis=1)
                    guess[anchored] = est[anchored]
                ok = ray_rows & np.isfinite(guess).all(axis=1)
                self._extrapolated |= ok & ~anchored  # nothing holds it along its ray: there it coasts to rest
                z[ok] = project_on_rays(guess[ok], rays[ok])
                if body is not None and self.config.ray_distances:
                    self._fit_rays(z, seen, rays, np.flatnonzero(ok & body.in_segment))
                flags[ok] = FillCase.RAY
                visible |= ok
        poses = None
        if body is not None:
            targets = ~visible & body.in_segment
            self._held = set()
            est, codes, (r, t, posed) = self._constrain(z, visible, prior, targets, near, keep=True)
            fresh = np.zeros(len(body.members), dtype=bool)
            fresh[near] = True
            poses = r, t, posed, fresh
            self._holds = {k: hold for k, hold in self._holds.items() if k in self._held}
            done = targets & np.isfinite(est).all(axis=1)
            if self._max_coast is not None:
                done &= ~self._extrapolated | (self._unmeasured < self._max_coast)
            z[done] = est[done]
            flags[done] = codes[done]
        lone = (flags == _MISSING) & np.isfinite(prior).all(axis=1)
        if self._max_coast is not None:
            lone &= self._unmeasured < self._max_coast
        z[lone] = prior[lone]
        flags[lone] = _KALMAN
        return poses

    def _fit_rays(self, z: np.ndarray, seen: np.ndarray, rays: np.ndarray, rows: np.ndarray) -> None:
        """Slide each single-camera marker along its ray to the point whose distances to the observed markers of its
        segment best match the segment's shape, held near its projected estimate (a few Gauss-Newton steps on the
        ray parameter). This is the line-circle (appendix D) and line-sphere (appendix E) solutions with the
        projected estimate of 5.3.5 as a prior, which picks the right intersection and steadies the near-tangent
        cases that made the thesis prefer the projection alone."""
        body = self.body
        assert body is not None
        prior_weight = (self.config.observed_sd / self.config.ray_sd) ** 2
        for i in rows:
            k = body.marker_seg[i]
            members = body.members[k]
            vis = seen[members]
            if not vis.any():
                continue
            slot = int(np.flatnonzero(members == i)[0])
            anchors = z[members[vis]]
            radii = np.linalg.norm(body.offsets[k][vis] - body.offsets[k][slot], axis=1)
            origin, direction = rays[i, :3], _unit(rays[i, 3:])
            start = float((z[i] - origin) @ direction)
            ray_s = start
            for _ in range(5):
                diff = origin + ray_s * direction - anchors
                dist = np.maximum(np.linalg.norm(diff, axis=1), 1e-9)
                grad = diff @ direction / dist
                step = -((dist - radii) @ grad + prior_weight * (ray_s - start)) / (grad @ grad + prior_weight)
                ray_s += step
                if abs(step) < 1e-4:
                    break
            z[i] = origin + ray_s * direction

    def _constrain(
        self, filled: np.ndarray, visible: np.ndarray, prior: np.ndarray, targets: np.ndarray, near: np.ndarray,
        keep: bool,
    ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Rigid-body estimates (5.3) of the ``targets`` markers from the ``visible`` ones: (N, 3), case codes, and
        the poses this frame (R, t, known) of the segments ``near`` the targets (holding one, or a neighbour of
        one; the others are left unknown): fitted to their visible markers when three or more are, else as placed
        here. ``keep`` stores the two-anchor holds (off for the single-camera pass)."""
        body = self.body
        assert body is not None
        cfg = self.config
        n = len(self.labels)
        est = np.full((n, 3), np.nan)
        codes = np.zeros(n, dtype=np.uint8)
        layout = body.layout(visible, targets, near)
        seg_vis, segments = layout.seg_vis, layout.segments
        r_all, t_all = np.zeros((len(body.members), 3, 3)), np.zeros((len(body.members), 3))
        posed = np.zeros(len(body.members), dtype=bool)
        r_all[near], t_all[near], posed[near] = layout.fit(filled)  # three visible markers fix a pose
        seen_posed = posed.copy()  # placed with at least one of their own markers visible
        direct = posed[layout.target_seg]  # per target: its segment is fitted
        if direct.any():
            rows, seg = layout.target_rows[direct], layout.target_seg[direct]
            est[rows] = (r_all[seg] @ layout.target_local[direct, :, None])[..., 0] + t_all[seg]
            codes[rows] = _ONE_MISSING
        pending = sorted(segments[~posed[segments]].tolist(), key=lambda k: -seg_vis[k])
        force = False  # set once no pending segment can be anchored: the rest keep their last rotation rate
        while pending:
            progress = False
            for k in list(pending):
                seen_rows, seen_offsets, seen_names, miss, hit = layout.parts[k]
                nv = int(seg_vis[k])
                links = [link for link in body.links[k] if posed[link[1]]]
                reference = None  # the first posed neighbour, preferring one placed with its own markers seen
                for _, other, _, _ in links:
                    if self._pose_ok[0, other] and (reference is None or seen_posed[other] > seen_posed[reference[0]]):
                        reference = (other, r_all[other], self._pose_r[0, other])
                if not (nv == 0 or cfg.joint_anchors == "partial"):
                    links = []
                m = nv + len(links)
                if m == 0 and not force:
                    continue  # a hidden neighbour may be placed first and anchor this segment
                p, a, w = np.empty((m, 3)), np.empty((m, 3)), np.ones(m)
                p[:nv], a[:nv] = filled[seen_rows], seen_offsets
                for i, (_, other, own, theirs) in enumerate(links, start=nv):
                    p[i], a[i], w[i] = r_all[other] @ theirs + t_all[other], own, cfg.joint_weight
                anchors = tuple(seen_names + [("joint", j) for j, *_ in links])
                via_seen = any(seen_posed[other] for _, other, _, _ in links)
                pending.remove(k)
                progress = True
                placed = self._estimate_segment(k, p, a, w, anchors, reference, prior, keep)
                if placed is None:
                    continue
                r, t, points_on_circle = placed
                est[miss] = (points_on_circle if points_on_circle is not None else body.offsets[k] @ r.T + t)[hit]
                if seg_vis[k] >= 2:
                    codes[miss] = FillCase.ONE_MISSING
                elif seg_vis[k] == 1:
                    codes[miss] = FillCase.TWO_MISSING
                elif via_seen:
                    codes[miss] = FillCase.VIA_JOINT
                else:
                    codes[miss] = FillCase.CONSTANT_ROTOR
                    self._extrapolated[miss] = len(p) == 0
                if len(p):
                    r_all[k], t_all[k], posed[k] = r, t, True
                    seen_posed[k] = seg_vis[k] > 0
            force = not progress
        return est, codes, (r_all, t_all, posed)

    def _estimate_segment(
        self, k: int, p: np.ndarray, a: np.ndarray, w: np.ndarray, anchors: tuple[tuple[str, int], ...],
        reference: tuple[int, np.ndarray, np.ndarray] | None, prior: np.ndarray, keep: bool,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
        """Pose (R, t) of segment ``k`` from anchor points ``p`` (world) at local ``a`` with weights ``w``, and for
        two anchors the markers placed on their two-sphere circles.

        The rotation left free by fewer than three anchors comes from the last frame, in the frame of a posed
        neighbour ``reference`` (its index, rotation now and one frame ago) when there is one, else in the world.
        Two anchors fix the axis through them: the rotation is the one held since the gap began, swung the least
        way that brings that axis where the anchors are now (a path-independent swing-twist split, so the twist about
        the axis cannot creep as the axis moves); ``anchors`` names them, so a new pair starts a new hold, which is
        stored when ``keep``. One anchor: the rotation relative to the reference is held, or the segment turns on
        by its last rotor (``hidden_rotation``). None: the last rotor and the markers' filtered centroid (5.3.4).
        """
        body = self.body
        assert body is not None
        offsets = body.offsets[k]
        if len(p) >= 3:
            fit = _fit_one(a, p, w)
            if fit is not None:
                return fit[0], fit[1], None
        if not self._pose_ok[0, k]:
            return None
        if reference is not None:
            ref, frame, frame_prev = reference
            relative = frame_prev.T @ self._pose_r[0, k]
        else:
            ref, frame, relative = -1, np.eye(3), self._pose_r[0, k]
        if len(p) >= 2:
            # 5.3.2 and appendix C, with the hold described above; each marker is then pulled onto its circle
            key = (ref, anchors[0], anchors[1])
            hold = self._holds.get(k)
            if hold is None or hold[0] != key:
                hold = (key, relative @ _unit(a[1] - a[0]), relative)
            if keep:
                self._holds[k] = hold
                self._held.add(k)
            r = frame @ _swing(hold[1], frame.T @ _unit(p[1] - p[0])) @ hold[2]
            t = 0.5 * (p[0] - r @ a[0] + p[1] - r @ a[1])
            m = len(offsets)
            placed = nearest_on_circle(np.repeat(p[:1], m, 0), np.repeat(p[1:2], m, 0),
                                       np.linalg.norm(offsets - a[0], axis=1), np.linalg.norm(offsets - a[1], axis=1),
                                       offsets @ r.T + t)
            return r, t, placed
        if len(p) == 1:  # 5.3.3 / 5.3.4: the rotated offset from the single anchor
            r = frame @ relative if reference is not None and self.config.hidden_rotation == "joint" else (
                self._rotor_prediction(k))
            return r, p[0] - r @ a[0], None
        centre = prior[body.members[k]]
        if not np.isfinite(centre).all():
            return None
        r = self._rotor_prediction(k)
        return r, centre.mean(axis=0) - r @ offsets.mean(axis=0), None

    def _rotor_prediction(self, k: int) -> np.ndarray:
        """Segment ``k``'s rotation one frame on, turned again by its last inter-frame rotor (5.3.4)."""
        last = self._pose_r[0, k]
        if not self._pose_ok[1, k]:
            return last
        step = Rotation.from_matrix(last @ self._pose_r[1, k].T)  # R_{k-1} R_{k-2}^T, re-orthonormalised
        return (step * Rotation.from_matrix(last)).as_matrix()

def joint_centres(body: _Body, poses: tuple[np.ndarray, np.ndarray, np.ndarray], flags: np.ndarray) -> np.ndarray:
    """Each joint's centre from the poses (R, t, known) of its two segments; from the side whose markers are all
    observed when only one side is (tables 6.1, 6.2: a centre from a segment with estimated markers is worse), the
    mean of both otherwise (eq. 4.29); NaN rows for joints the body cannot use."""
    out = np.full((len(body.joints), 3), np.nan)
    if not len(body.joint_segments):
        return out
    r, t, known = poses
    seg = body.joint_segments  # (J, 2)
    ends = (r[seg] @ body.joint_offsets[..., None])[..., 0] + t[seg]  # (J, 2, 3)
    full = (np.append(flags == _OBSERVED, False)[body.idx] | ~body.slot).all(axis=1)[seg]
    weight = known[seg] * np.where(full.any(axis=1, keepdims=True), full, True)
    total = weight.sum(axis=1)
    centre = np.einsum("jk,jki->ji", weight, ends) / np.maximum(total, 1)[:, None]
    out[body.joint_usable] = np.where(total[:, None] > 0, centre, np.nan)
    return out


def fill_sequence(
    positions: np.ndarray, labels: list[str], rate: float, config: FillerConfig | None = None,
    skeleton: SkeletonModel | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Fill a whole recording (F, N, 3) frame by frame, exactly as a live stream would; returns positions and flags."""
    positions = np.asarray(positions, dtype=float)
    filler = GapFiller(labels, rate, config, skeleton)
    out = np.full(positions.shape, np.nan)
    flags = np.zeros(positions.shape[:2], dtype=np.uint8)
    for f in range(len(positions)):
        result = filler.update(positions[f])
        out[f], flags[f] = result.positions, result.flags
    return out, flags
