"""Simulated optical motion capture of an articulated rig, with its ground truth.

The rig moves with smooth, lifelike motion (sums of sinusoids at incommensurate frequencies, or a BVH recording
retargeted onto the rig) and is observed with Gaussian noise, soft-tissue artefact, dropouts, long gaps, hidden
segments and ghost points, either as labelled rows or as an unlabelled shuffled point cloud.

With ``cameras`` > 0 an optical camera model decides what the tracker sees. The cameras stand evenly spaced on a
horizontal circle around the centre of the volume (the first on the +x axis), each aimed at a point 1 m above the
floor at the centre, with a cone of view of 35 degrees half-angle. The body occludes them: every segment is a
capsule whose axis runs from its proximal joint centre to the proximal joint of its first child (a leaf segment's
to just beyond its markers' centroid) and whose radius is a little smaller than the distance of its nearest marker
from that axis, as markers sit on the skin. A camera sees a marker inside its cone when the line of sight from the
marker (leaving out the first few millimetres) to the camera centre passes outside every capsule, so a marker on the
far side of its own limb, or behind another limb or the trunk, is hidden from that camera. A marker hidden by an
occlusion schedule is seen by no camera, and ``camera_dropout`` makes each camera miss each marker at random. A
marker seen by two cameras or more is observed as a point; one seen by a single camera arrives as a ray from that
camera's centre through its noisy position, and is missing from the points (an unlabelled cloud lists it as an extra
row with a ray and no position, after the points); one seen by none is missing.

Every frame is a pure function of (config, frame index): its randomness is drawn for its block of frames, seeded by
(seed, block), and occlusion schedules by (seed, kind, block of frames), so frames can be produced in any order, live
or offline, and a restarted simulator resumes exactly where it stopped.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from scipy.spatial.transform import Rotation

from mocapflow.mocap.model import Joint, Segment, SkeletonModel
from mocapflow.mocap.motion import Bvh, BvhMotion, SyntheticMotion, forward_kinematics
from mocapflow.mocap.report import Progress, steps
from mocapflow.mocap.rigs import RIG_NAMES, Rig, make_rig

# Random streams: the second entropy word of each generator, so streams never share draws.
_FRAME, _DROPOUT, _LONG_GAP, _HIDDEN, _MOTION, _SKIN = range(6)
_BLOCK_S = 10.0  # occlusion schedules are drawn per block of this many seconds
_BLOCK = 64  # frames worked out together: poses, positions and random draws
_DROPOUT_FRAMES = (2, 10)  # length of a short dropout, frames
_LONG_GAP_S = (1.0, 4.0)  # length of a long gap, s
_HIDDEN_S = (2.0, 6.0)  # length of a hidden-segment period, s
_HIDDEN_PER_S = 0.1  # hidden periods starting per hidden segment per second
_GHOST_MM = (20.0, 300.0)  # distance of a ghost from the marker it appears near
_CAMERA_AIM_MM = 1000.0  # cameras aim at this height above the centre of the floor
_CAMERA_HALF_FOV = np.radians(35.0)  # half-angle of a camera's cone of view
_LEAF_REACH = 1.3  # a leaf segment's capsule axis reaches this many times its markers' centroid from its joint
_SKIN_FRACTION = 0.8  # capsule radius as a fraction of its nearest marker's distance from the axis
_SIGHT_CLEAR_MM = 5.0  # the part of a line of sight next to its marker that no capsule blocks


class SimulatorConfig(BaseModel):
    """What to simulate and how it is observed."""

    model_config = ConfigDict(extra="forbid")

    rig: str = Field(default="human", description=f"articulated body: {', '.join(RIG_NAMES)}")
    rate: float = Field(default=240.0, gt=0, le=2000, description="frame rate, Hz")
    seed: int = Field(default=0, ge=0, description="seed of the motion, noise, occlusions and ghosts")
    noise_mm: float = Field(default=0.5, ge=0, description="sd of isotropic Gaussian measurement noise, mm")
    skin_mm: float = Field(
        default=0.0, ge=0, description="soft-tissue artefact amplitude, mm (smooth, driven by the adjacent joints)"
    )
    dropout_rate: float = Field(
        default=0.0, ge=0, description="short dropouts (2-10 frames) starting per marker per second"
    )
    long_gaps: float = Field(default=0.0, ge=0, description="long gaps (1-4 s) starting per marker per minute")
    hidden_segments: list[str] = Field(
        default=[], description="segments whose markers all vanish together for 2-6 s periods (~1/3 of the time)"
    )
    ghosts: float = Field(
        default=0.0, ge=0, description="mean number of ghost points per frame (Poisson), in unlabelled mode"
    )
    unlabelled: bool = Field(default=False, description="publish a shuffled, unlabelled point cloud with ghosts")
    bvh: str | None = Field(default=None, description="BVH file whose motion drives the human rig")
    cameras: int = Field(
        default=0, ge=0,
        description="cameras on a circle around the volume, occluded by the body; a marker seen by one camera arrives "
                    "as a ray; 0: no camera model, markers are seen unless a gap hides them",
    )
    camera_radius_mm: float = Field(default=4000.0, gt=0, description="distance of the cameras from the centre, mm")
    camera_height_mm: float = Field(default=2500.0, description="height of the cameras above the floor, mm")
    camera_dropout: float = Field(
        default=0.0, ge=0, le=1, description="chance that a camera misses a marker it could see, per frame"
    )

    @field_validator("rig")
    @classmethod
    def _known_rig(cls, rig: str) -> str:
        if rig not in RIG_NAMES:
            raise ValueError(f"unknown rig {rig!r}; choose one of {', '.join(RIG_NAMES)}")
        return rig

    @model_validator(mode="after")
    def _consistent(self) -> SimulatorConfig:
        segments = make_rig(self.rig).segments
        unknown = [s for s in self.hidden_segments if s not in segments]
        if unknown:
            raise ValueError(f"hidden_segments {unknown} are not segments of rig {self.rig!r}: {', '.join(segments)}")
        if self.bvh is not None and self.rig != "human":
            raise ValueError("bvh drives the human rig only")
        return self


@dataclass
class SimFrame:
    """One observed frame and its truth."""

    frame: int
    time: float  # s, = frame / rate
    points: np.ndarray  # labelled: (N, 3) in marker order, NaN where occluded; unlabelled: (M, 3) shuffled
    labels: list[str] | None  # marker labels when labelled, None when unlabelled
    identity: np.ndarray  # (rows of points,) true marker index of each row, -1 for a ghost
    true_positions: np.ndarray  # (N, 3) noise-free positions, soft-tissue artefact included
    visible: np.ndarray  # (N,) bool, observed as a point
    joint_centres: np.ndarray  # (J, 3) world joint centres, J = S - 1
    rays: np.ndarray | None  # single-camera rays (origin, unit direction) per row of points, NaN rows where none
    # (unlabelled: extra rows with no position after the points); None without cameras


@dataclass
class _Block:
    """Frames ``index * _BLOCK`` to ``(index + 1) * _BLOCK - 1`` (row k: the block's k-th frame)."""

    index: int
    rot: np.ndarray  # (B, S, 3, 3) segment rotations
    pos: np.ndarray  # (B, S, 3) segment origins
    true: np.ndarray  # (B, N, 3) noise-free marker positions
    observed: np.ndarray  # (B, N, 3) with noise
    misses: np.ndarray | None  # (B, N, C) True where a camera misses a marker at random (camera_dropout)
    ghost_rows: np.ndarray  # (B + 1,) frame k's ghosts are rows ghost_rows[k]:ghost_rows[k + 1] of ghosts
    ghosts: np.ndarray  # (G, 3)
    shuffle: np.ndarray  # (B, N + most ghosts) random keys: a frame's points are ordered by the keys of its rows
    hidden: np.ndarray  # (B, N) True where a marker is occluded (the occlusion schedules)
    clouds: tuple[np.ndarray, np.ndarray, np.ndarray] | None  # unlabelled without cameras: ``_clouds`` of the block


@dataclass
class SimRecording:
    """A run of frames in batch form: the labelled view, with the unlabelled views when the config is unlabelled."""

    rate: float
    labels: list[str]
    positions: np.ndarray  # (F, N, 3) observed (noisy), NaN where occluded
    true_positions: np.ndarray  # (F, N, 3)
    visible: np.ndarray  # (F, N) bool
    joint_names: list[str]
    joint_centres: np.ndarray  # (F, J, 3)
    joint_parent: list[str]  # parent segment of each joint
    joint_child: list[str]  # child segment of each joint
    marker_segment: list[str]  # segment of each marker
    points: list[np.ndarray] | None  # unlabelled point clouds per frame
    identity: list[np.ndarray] | None  # their true marker indices, -1 for ghosts
    rays: np.ndarray | None  # (F, N, 6) single-camera rays in marker order, NaN where none; None without cameras


class _Gaps:
    """Occlusion periods of one kind: events start at a constant rate per unit (a marker or a segment's markers)
    and last a random number of frames. Events are drawn per block of frames from (seed, stream, block)."""

    def __init__(self, seed: int, stream: int, units: np.ndarray, per_frame: float, lengths: tuple[int, int],
                 block: int) -> None:
        self.seed, self.stream, self.units, self.per_frame = seed, stream, units, per_frame
        self.lengths, self.block = lengths, block
        self.lookback = -(-lengths[1] // block)
        self.cache: dict[int, np.ndarray] = {}

    def _starting(self, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rng = np.random.default_rng([self.seed, self.stream, b])
        counts = rng.poisson(self.per_frame * self.block, len(self.units))
        unit = np.repeat(np.arange(len(self.units)), counts)
        start = b * self.block + rng.integers(0, self.block, len(unit))
        return unit, start, start + rng.integers(self.lengths[0], self.lengths[1] + 1, len(unit))

    def _hidden_in(self, b: int) -> np.ndarray:
        """(block, N) True for markers occluded in each frame of block b, by the events of that block and of those
        before it that last into it (worked out once a block: a frame then costs one row)."""
        if b not in self.cache:
            if len(self.cache) > 1:
                self.cache.clear()
            first = b * self.block
            mask = np.zeros((self.block, self.units.shape[1]), bool)
            for k in range(max(b - self.lookback, 0), b + 1):
                for unit, start, stop in zip(*self._starting(k), strict=True):
                    if stop > first:
                        mask[max(start - first, 0):stop - first] |= self.units[unit]
            self.cache[b] = mask
        return self.cache[b]

    def hidden(self, first: int, count: int) -> np.ndarray:
        """(count, N) True for markers occluded in frames first..first + count - 1."""
        rows, i, end = [], first, first + count
        while i < end:
            b, k = divmod(i, self.block)
            take = min(self.block - k, end - i)
            rows.append(self._hidden_in(b)[k:k + take])
            i += take
        return np.concatenate(rows)


class Simulator:
    """Random-access frame source: ``frame(i)`` depends only on the config and i."""

    def __init__(self, config: SimulatorConfig, bvh: Bvh | None = None) -> None:
        """``bvh``: the motion file named by ``config.bvh``, read by the caller (``mocapflow.io.bvh.read_bvh``)."""
        if (config.bvh is None) != (bvh is None):
            raise ValueError("pass the BVH motion exactly when config.bvh names one")
        self.config = config
        self.rig = rig = make_rig(config.rig)
        self.joint_names = list(rig.joint_names[1:])
        self.labels = list(rig.marker_labels)
        n = len(rig.marker_labels)
        self._motion: SyntheticMotion | BvhMotion = SyntheticMotion(rig, [config.seed, _MOTION])
        if bvh is not None:
            self._motion = BvhMotion(rig, bvh)
        self._skin = _skin_matrix(rig, config.seed) * config.skin_mm if config.skin_mm > 0 else None
        block = max(1, round(_BLOCK_S * config.rate))
        rate = config.rate
        markers = np.eye(n, dtype=bool)
        self._gaps: list[_Gaps] = []
        if config.dropout_rate > 0:
            self._gaps.append(_Gaps(config.seed, _DROPOUT, markers, config.dropout_rate / rate, _DROPOUT_FRAMES, block))
        if config.long_gaps > 0:
            lengths = (max(1, round(_LONG_GAP_S[0] * rate)), max(1, round(_LONG_GAP_S[1] * rate)))
            self._gaps.append(_Gaps(config.seed, _LONG_GAP, markers, config.long_gaps / 60 / rate, lengths, block))
        if config.hidden_segments:
            seg = [rig.segments.index(s) for s in config.hidden_segments]
            units = rig.marker_segment[None, :] == np.array(seg)[:, None]
            lengths = (max(1, round(_HIDDEN_S[0] * rate)), max(1, round(_HIDDEN_S[1] * rate)))
            self._gaps.append(_Gaps(config.seed, _HIDDEN, units, _HIDDEN_PER_S / rate, lengths, block))
        self.camera_centres = camera_ring(config.cameras, config.camera_radius_mm, config.camera_height_mm)
        aim = np.array([0.0, 0.0, _CAMERA_AIM_MM]) - self.camera_centres
        self._camera_axes = aim / np.linalg.norm(aim, axis=1, keepdims=True)
        self.capsule_ends, self.capsule_radii = _capsules(rig)
        self._block = _Block(-1, *(np.empty(0),) * 9, None)
        self._ahead: tuple[int, Iterator[_Block | None]] | None = None  # a block being worked out, step by step
        self._ready: _Block | None = None  # ... and once it is

    def _block_of(self, i: int) -> _Block:
        """The block of _BLOCK frames that frame i falls in (``_work``), worked out now if it was not ahead."""
        if i < 0:
            raise ValueError(f"frame index must be >= 0, got {i}")
        b = i // _BLOCK
        if self._block.index != b:
            self._step(b, whole=True)
            assert self._ready is not None
            self._block, self._ready = self._ready, None
        return self._block

    def _step(self, b: int, whole: bool) -> None:
        """Work out block b: one step of it, or (``whole``) all that is left; done, it is ``self._ready``."""
        if self._ready is not None and self._ready.index == b:
            return
        if self._ahead is None or self._ahead[0] != b:
            self._ahead = (b, self._work(b))
        for done in self._ahead[1]:
            if done is not None:
                self._ready, self._ahead = done, None
                return
            if not whole:
                return

    def _work(self, b: int) -> Iterator[_Block | None]:
        """Block b, vectorised over its frames, worked out in steps of a few tenths of a millisecond (None after each,
        the block last): segment poses, true and noisy marker positions, and every random draw of its frames, from a
        generator seeded by (seed, block). So frame i is the same whatever was asked before it, and a frame costs a
        few slices."""
        cfg, rig = self.config, self.rig
        root, rotvec = self._motion(np.arange(b * _BLOCK, (b + 1) * _BLOCK) / cfg.rate)
        local = Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(*rotvec.shape, 3)
        yield None
        rot, pos = forward_kinematics(rig, local, root)
        yield None
        offsets = np.broadcast_to(rig.marker_offsets, (_BLOCK, *rig.marker_offsets.shape))
        if self._skin is not None:
            offsets = offsets + (np.sin(rotvec.reshape(_BLOCK, -1)) @ self._skin.T).reshape(_BLOCK, -1, 3)
        seg = rig.marker_segment
        true = (rot[:, seg] @ offsets[..., None])[..., 0] + pos[:, seg]
        yield None
        rng = np.random.default_rng([cfg.seed, _FRAME, b])
        observed = true + rng.standard_normal(true.shape) * cfg.noise_mm
        n = len(seg)
        misses = rng.random((_BLOCK, n, cfg.cameras)) < cfg.camera_dropout if cfg.camera_dropout > 0 else None
        counts = rng.poisson(cfg.ghosts, _BLOCK) if cfg.unlabelled and cfg.ghosts > 0 else np.zeros(_BLOCK, int)
        direction = rng.standard_normal((counts.sum(), 3))
        direction /= np.sqrt((direction * direction).sum(1, keepdims=True))
        radius = rng.uniform(*_GHOST_MM, (len(direction), 1))
        near = rng.integers(0, n, len(direction))
        ghosts = true[np.repeat(np.arange(_BLOCK), counts), near] + direction * radius
        shuffle = rng.random((_BLOCK, n + counts.max(initial=0))) if cfg.unlabelled else np.empty((_BLOCK, 0))
        ghost_rows = np.concatenate([[0], np.cumsum(counts)])
        hidden = np.zeros((_BLOCK, n), bool)
        for gaps in self._gaps:
            hidden |= gaps.hidden(b * _BLOCK, _BLOCK)
        yield None
        # without cameras what a frame shows is known now; with them, each frame works out which cameras see what
        clouds = _clouds(observed, ~hidden, ghosts, ghost_rows, shuffle) if cfg.unlabelled and not cfg.cameras else None
        yield _Block(b, rot, pos, true, observed, misses, ghost_rows, ghosts, shuffle, hidden, clouds)

    def prepare(self, i: int) -> None:
        """One step of the work ahead (``_work``): frame i's block if not worked out yet, else the next one. A live
        source calls it after each frame, so that a block's few milliseconds are spread over its first frames
        instead of delaying one of them by all of it."""
        b = i // _BLOCK
        self._step(b if self._block.index != b else b + 1, whole=False)

    def segment_poses(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """World pose of every segment's rig frame (origin at its proximal joint centre): R (S, 3, 3), t (S, 3)."""
        block, k = self._block_of(i), i % _BLOCK
        return block.rot[k], block.pos[k]

    def frame(self, i: int) -> SimFrame:
        """Frame i as the tracker reports it, with its truth."""
        cfg = self.config
        block, k = self._block_of(i), i % _BLOCK
        rot, pos, true, observed = block.rot[k], block.pos[k], block.true[k], block.observed[k]
        visible = ~block.hidden[k]
        rays = None
        if cfg.cameras:
            seen = self._seen(true, rot, pos) & visible[:, None]
            if block.misses is not None:
                seen &= ~block.misses[k]
            seen_by = seen.sum(1)
            visible = seen_by >= 2
            origin = self.camera_centres[seen.argmax(1)]
            direction = observed - origin
            direction /= np.linalg.norm(direction, axis=1, keepdims=True)
            rays = np.where((seen_by == 1)[:, None], np.concatenate([origin, direction], axis=1), np.nan)
        if cfg.unlabelled:
            if block.clouds is None:  # this frame's alone, its visibility known only now
                rows = block.ghost_rows[k:k + 2]
                clouds = _clouds(observed[None], visible[None], block.ghosts[rows[0]:rows[1]], rows - rows[0],
                                 block.shuffle[k:k + 1])
                row = 0
            else:
                clouds, row = block.clouds, k
            count = clouds[2][row]
            points, identity, labels = clouds[0][row, :count].copy(), clouds[1][row, :count].copy(), None
            if rays is not None:  # single-camera markers follow the points, as rows with a ray and no position
                single = np.flatnonzero(np.isfinite(rays[:, 0]))
                # ordered by keys from the other end of the frame's, which no row of points shares
                single = single[np.argsort(block.shuffle[k, ::-1][:len(single)])]
                rays = np.concatenate([np.full((len(points), 6), np.nan), rays[single]])
                points = np.concatenate([points, np.full((len(single), 3), np.nan)])
                identity = np.concatenate([identity, single])
        else:
            points = np.where(visible[:, None], observed, np.nan)
            identity, labels = np.arange(len(true)), self.labels
        # copies of the block's rows: a caller may change its frame, the block's later frames stay as drawn
        return SimFrame(frame=i, time=i / cfg.rate, points=points, labels=labels, identity=identity,
                        true_positions=true.copy(), visible=visible, joint_centres=pos[1:].copy(), rays=rays)

    def _seen(self, markers: np.ndarray, rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """(N, C) True where a camera sees a marker at ``markers`` (N, 3): inside its cone of view, with a line of
        sight clear of every segment's capsule (segment poses R (S, 3, 3), t (S, 3)).

        The line of sight is m + a u (u the unit vector towards the camera, a from _SIGHT_CLEAR_MM to the camera's
        distance L) and a capsule's axis q + b v (b in [0, 1]). Their closest points are found as for any two line
        segments: the a closest to the other line, clamped; the b closest to that point, clamped; the a closest to
        that, clamped. Everything is dot products of (S, C, N) arrays."""
        cams, axes = self.camera_centres, self._camera_axes
        mm = (markers * markers).sum(1)
        cm = cams @ markers.T  # (C, N)
        length = np.sqrt((cams * cams).sum(1)[:, None] - 2 * cm + mm)
        in_view = axes @ markers.T - (axes * cams).sum(1)[:, None] > np.cos(_CAMERA_HALF_FOV) * length
        v = np.einsum("sij,sj->si", rot, self.capsule_ends)
        vv = (v * v).sum(1)[:, None, None]
        vm, qm = v @ markers.T, pos @ markers.T  # (S, N)
        vr = (vm - (v * pos).sum(1)[:, None])[:, None]  # v.(m - q), (S, 1, N)
        rr = (mm - 2 * qm + (pos * pos).sum(1)[:, None])[:, None]  # |m - q|^2
        uv = ((v @ cams.T)[..., None] - vm[:, None]) / length  # u.v, (S, C, N)
        ur = (cm - mm - (pos @ cams.T)[..., None] + qm[:, None]) / length  # u.(m - q)
        a = np.clip((uv * vr - ur * vv) / np.maximum(vv - uv * uv, 1e-9), _SIGHT_CLEAR_MM, length)
        b = np.clip((uv * a + vr) / vv, 0, 1)
        nearest = uv * b - ur
        a = np.clip(nearest, _SIGHT_CLEAR_MM, length)
        gap2 = rr - b * (2 * vr - b * vv) + a * (a - 2 * nearest)  # |m + a u - q - b v|^2
        return (in_view & ~(gap2 < self.capsule_radii[:, None, None] ** 2).any(0)).T


def _clouds(observed: np.ndarray, visible: np.ndarray, ghosts: np.ndarray, ghost_rows: np.ndarray,
            keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frames as an unlabelled tracker reports them: each frame's visible markers (``observed`` (F, N, 3) where
    ``visible`` (F, N)) and its ghosts (rows ``ghost_rows[k]:ghost_rows[k + 1]`` of ``ghosts`` for frame k), in the
    order of the frame's random ``keys`` (F, W) (the visible markers' in marker order, then the ghosts'). Returns the
    points (F, W, 3), their true marker indices (F, W), -1 for a ghost, and the rows in use in each frame (F,)."""
    frames, n = visible.shape
    width = keys.shape[1]
    seen = visible.sum(1)
    counts = seen + np.diff(ghost_rows)
    which = np.argsort(~visible, axis=1, kind="stable")  # each frame's visible markers first, in marker order
    used = np.arange(n)[None] < seen[:, None]
    identity = np.full((frames, width), -1, np.intp)
    points = np.full((frames, width, 3), np.nan)
    identity[:, :n][used] = which[used]
    points[:, :n][used] = np.take_along_axis(observed, which[..., None], 1)[used]
    owner = np.repeat(np.arange(frames), np.diff(ghost_rows))  # the frame of each ghost, after its markers
    points[owner, seen[owner] + np.arange(len(owner)) - ghost_rows[owner]] = ghosts
    # the rows in use sorted by their keys (distinct random numbers), the rows beyond after them
    order = np.argsort(np.where(np.arange(width)[None] < counts[:, None], keys, np.inf), axis=1)
    return np.take_along_axis(points, order[..., None], 1), np.take_along_axis(identity, order, 1), counts


def camera_ring(cameras: int, radius_mm: float, height_mm: float) -> np.ndarray:
    """(C, 3) centres of ``cameras`` evenly spaced on a horizontal circle about the vertical axis through the origin,
    the first on +x."""
    azimuth = 2 * np.pi * np.arange(cameras) / max(cameras, 1)
    return np.stack([radius_mm * np.cos(azimuth), radius_mm * np.sin(azimuth), np.full(cameras, height_mm)], axis=1)


def _capsules(rig: Rig) -> tuple[np.ndarray, np.ndarray]:
    """Every segment's capsule: the end of its axis in the segment's frame (S, 3), the axis starting at the frame's
    origin, and its radius (S,), a little smaller than the distance of the segment's nearest marker from the axis."""
    nseg = len(rig.segments)
    ends = np.empty((nseg, 3))
    for s in range(nseg):
        children = np.flatnonzero(rig.parents == s)
        centroid = rig.marker_offsets[rig.marker_segment == s].mean(0)
        ends[s] = rig.joint_offsets[children[0]] if len(children) else _LEAF_REACH * centroid
    axis = ends[rig.marker_segment]
    along = np.clip((rig.marker_offsets * axis).sum(1) / (axis * axis).sum(1), 0, 1)
    distance = np.linalg.norm(rig.marker_offsets - along[:, None] * axis, axis=1)
    radii = np.array([distance[rig.marker_segment == s].min() for s in range(nseg)]) * _SKIN_FRACTION
    return ends, radii


def _skin_matrix(rig: Rig, seed: int) -> np.ndarray:
    """(N*3, S*3) map from the sines of joint rotation-vector components to marker displacements in segment frames.

    Each marker moves with the joints at either end of its segment, along a random direction per joint component,
    so the artefact is smooth and correlated with joint motion like real soft tissue. Scaled by skin_mm, the
    displacement reaches about skin_mm (human rig: RMS 0.44, 99th percentile 0.9 times skin_mm).
    """
    rng = np.random.default_rng([seed, _SKIN])
    n, s = len(rig.marker_labels), len(rig.segments)
    out = np.zeros((n, 3, s, 3))
    for m, seg in enumerate(rig.marker_segment):
        joints = [j for j in range(1, s) if j == seg or rig.parents[j] == seg]
        for j in joints:
            d = rng.standard_normal((3, 3))
            out[m, :, j, :] = d / np.linalg.norm(d, axis=0) / np.sqrt(3 * len(joints))
    return out.reshape(n * 3, s * 3)


def simulate(config: SimulatorConfig, frames: int, bvh: Bvh | None = None, *,
             progress: Progress | None = None) -> SimRecording:
    """Run the simulator over frames 0..frames-1 and gather the batch form."""
    sim = Simulator(config, bvh)
    rig = sim.rig
    n, j = len(rig.marker_labels), len(sim.joint_names)
    positions = np.full((frames, n, 3), np.nan)
    true = np.empty((frames, n, 3))
    visible = np.empty((frames, n), bool)
    centres = np.empty((frames, j, 3))
    points: list[np.ndarray] | None = [] if config.unlabelled else None
    identity: list[np.ndarray] | None = [] if config.unlabelled else None
    rays = np.full((frames, n, 6), np.nan) if config.cameras else None
    for i in steps(range(frames), frames, "simulate", progress):
        f = sim.frame(i)
        true[i], visible[i], centres[i] = f.true_positions, f.visible, f.joint_centres
        marker = f.identity >= 0
        positions[i, f.identity[marker]] = f.points[marker]
        if points is not None and identity is not None:
            points.append(f.points)
            identity.append(f.identity)
        if rays is not None and f.rays is not None:
            rays[i, f.identity[marker]] = f.rays[marker]
    return SimRecording(
        rate=config.rate, labels=list(rig.marker_labels), positions=positions, true_positions=true, visible=visible,
        joint_names=sim.joint_names, joint_centres=centres,
        joint_parent=[rig.segments[rig.parents[s]] for s in range(1, len(rig.segments))],
        joint_child=list(rig.segments[1:]), marker_segment=[rig.segments[s] for s in rig.marker_segment],
        points=points, identity=identity, rays=rays,
    )


def truth_skeleton(rig: Rig, reference_positions: np.ndarray) -> SkeletonModel:
    """The rig as a SkeletonModel in mocapflow's conventions, with the pose of ``reference_positions`` (N, 3) as the
    reference pose: the exact answer calibration and gap filling should find."""
    ref = np.asarray(reference_positions, float)
    if ref.shape != rig.marker_offsets.shape or not np.isfinite(ref).all():
        raise ValueError(f"reference positions must be a finite {rig.marker_offsets.shape} array")
    nseg = len(rig.segments)
    rot, pos, centroid = np.empty((nseg, 3, 3)), np.empty((nseg, 3)), np.empty((nseg, 3))
    segments = []
    for s, name in enumerate(rig.segments):
        idx = np.flatnonzero(rig.marker_segment == s)
        centroid[s] = ref[idx].mean(0)
        local = rig.marker_offsets[idx]
        fit, _ = Rotation.align_vectors(ref[idx] - centroid[s], local - local.mean(0))
        rot[s] = fit.as_matrix()
        pos[s] = centroid[s] - rot[s] @ local.mean(0)
        segments.append(Segment(name=name, markers=[rig.marker_labels[m] for m in idx],
                                marker_offsets=[tuple(v) for v in (ref[idx] - centroid[s]).tolist()]))
    joints = []
    for s in range(1, nseg):
        p = rig.parents[s]
        centre = 0.5 * (rot[p] @ rig.joint_offsets[s] + pos[p] + pos[s])  # as seen from the parent and the child
        hinge = rig.joint_kinds[s] == "hinge"
        joints.append(Joint(
            name=rig.joint_names[s], parent=rig.segments[p], child=rig.segments[s], kind="hinge" if hinge else "ball",
            parent_offset=tuple((centre - centroid[p]).tolist()), child_offset=tuple((centre - centroid[s]).tolist()),
            axis=tuple((rot[p] @ rig.hinge_axes[s]).tolist()) if hinge else None,
        ))
    return SkeletonModel(name=rig.name, segments=segments, joints=joints, root=rig.segments[0])
