"""Labelling from a skeleton: every point named with the skeleton's own marker names, by fitting its segments.

A skeleton (``mocapflow calibrate`` on a labelled range-of-motion trial) holds each segment's marker layout in its
local frame and the joints that link the segments. A new trial of the same subject is then labelled frame by frame,
whatever the point order and however long a marker was hidden:

1. markers seen in the previous frame follow their points (constant-velocity prediction, gated optimal assignment);
2. each segment's pose is fitted, surest first (one compiled pass over the segments): to three or more of its matched
   markers, else to its markers and the centres of its joints to surely posed segments (a segment reduced to two
   markers, or one, is posed through its joints), else to two points and, with a tiny weight, its pose of the previous
   frame, carried by a neighbour's motion where it has a posture to it (which only settles the turn about their line). A
   marker far from where the fit puts it gives its point back (a swap, a ghost), and so do all of a segment's markers
   when the fit puts a joint centre far from where its neighbour does;
3. the markers of posed segments not matched yet are predicted from the pose, and the points left over are assigned to
   these predictions by cost (distance, inside ``gate_mm``): a returning marker takes its own slot in the layout,
   whatever marker happens to lie near it. A segment posed through joints or its previous pose gives a point (inside
   ``weak_gate_mm``) only to a marker whose layout distances to the segment's seen markers and joint centres it keeps,
   and only when neither has another such candidate. A segment posed by three markers or more first takes back, for its
   markers, the points there that markers of segments with no pose hold (``_reclaim``): such a marker only follows its
   point from frame to frame;
4. a segment with no pose (the first frame, or after its markers and its neighbours' were hidden) is searched for among
   the points left over, and its own markers matched so far, by its layout (``_place_layout``): points at the layout's
   distances and its joint centres where its posed neighbours put them, placed by a proper rotation, taken when one
   placement fits clearly best, or, among placements of a symmetric layout that fit alike, turns the segment clearly
   least from its last posture to its neighbours. With no posed neighbour it takes four points, or three: near where it
   was lately, or, for a segment of three markers, once every segment with a triangle like its own (the other foot) is
   surely posed elsewhere. The last rule takes any triangle at the layout's distances, one across two segments of
   another limb among them: a segment with joints placed by it stands only if, by the end of the frame, a neighbour is
   surely posed with their joint centre where it puts it, or, no neighbour posed at all, once it has been so placed, at
   the same place, in every frame for ``held_s`` (a chance triangle across a joint keeps its shape only while the joint
   keeps still). A segment placed with a joint centre farther from a surely posed segment than the segments between
   them reach stands only in that second way, whatever its neighbours say, and until then no neighbour is placed
   through its joints. When nothing else poses a segment, a segment of three markers whose look-alike has no pose
   either (both feet unposed, a deadlock) is placed on three points together with an unposed neighbour whose own three
   points or more (both, for a neighbour of two markers) lie where the joint puts them (``_pair``);
5. a segment posed by three of its markers or more is placed anew where its layout lands on more points, its own and
   those left over, its joint centres where segments posed so put them (``_challenge``): one placed on chance points
   (at a cold start) and followed on them is found again where its own markers show.

Steps 2-5 repeat while they pose new segments, so a segment found in step 4 poses its neighbours through their
joints. Points that fit no marker (ghosts, markers the skeleton does not know) stay unnamed.

The names then go with the points' tracks, as the labeller without a model follows them: frame by frame as far as the
frames so far tell (``TrackedModelLabeller``, the live node's), or over a whole recording, by runs of trajectories
(``label_with_skeleton``); in both, where no frame alone names a run, by what its frames tell together. The method, its
workflow and its accuracy under stress: docs/labelling.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from itertools import combinations, permutations

import numpy as np
from numba import njit
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial.transform import Rotation

from mocapflow.mocap.labelling.assignment import assign, distance, gated_cost, gated_cost_compiled, match, norm
from mocapflow.mocap.labelling.config import FRAME_ACCEL_MM_S2, LabellerConfig, frame_gate
from mocapflow.mocap.labelling.evidence import RunningEvidence, Tables, name_by_evidence
from mocapflow.mocap.labelling.labeller import Labeller, own_gates
from mocapflow.mocap.labelling.offline import label_sequence, run_starts, source_rows
from mocapflow.mocap.labelling.tracks import observed
from mocapflow.mocap.model import SkeletonModel
from mocapflow.mocap.report import Progress, steps
from mocapflow.mocap.rigidfit import kabsch_into, place

PRIOR_WEIGHT = 1e-3
"""Weight of a segment's previous pose in its fit, against 1 for each marker or joint centre seen now."""
JOINT_WEIGHT = 0.1
"""Weight of a joint centre in a segment's fit: a joint is less sure than a marker."""
POSTURE_DEG = 30.0
"""How much farther than the best one (degrees) from the segment's last posture a rival placement must turn it."""


class ModelLabellerConfig(BaseModel):
    """Tolerances of the labeller that names points from a skeleton (mm, s)."""

    model_config = ConfigDict(extra="forbid")

    follow_mm: float = Field(40.0, gt=0, description="largest distance from where a marker seen in the previous frame "
                             "is expected (at constant velocity) to the point it follows: a foot or a hand at 10 m/s "
                             "strays 20 mm from it at 120 Hz")
    frame_accel_mm_s2: float = Field(FRAME_ACCEL_MM_S2, ge=0, description="acceleration between two frames that a "
                                     "followed marker may have: where frames are far apart (below 87 Hz by default), "
                                     "a moving marker's follow_mm widens by as far as it moved in its last frame, up "
                                     "to this times the frame interval squared (83 mm at 60 Hz)")
    gate_mm: float = Field(30.0, gt=0, description="largest distance from a marker's place in its segment's pose to "
                           "the point it takes")
    fit_mm: float = Field(10.0, gt=0, description="largest distance between a fitted layout and a point it keeps")
    spread_sigmas: float = Field(3.0, ge=0, description="a marker known to stray (its calibration spread) has fit_mm "
                                 "widened to this many times its spread, and gate_mm by as much; its weight in the "
                                 "fits falls as the square of that widening")
    weak_gate_mm: float = Field(150.0, gt=0, description="gate_mm for a segment posed through joints or its previous "
                                "pose")
    joint_mm: float = Field(40.0, gt=0, description="largest distance between a joint centre placed by each of its "
                            "two segments; a joint whose segments disagreed more in calibration (its gap_mm) has it "
                            "widened to spread_sigmas times that, and its weight in the fits falls as for a marker")
    max_coast_s: float = Field(0.1, ge=0, description="a marker whose segment has no pose is coasted at constant "
                               "velocity this long")
    recent_s: float = Field(2.0, ge=0, description="a segment posed this recently is looked for near where it was")
    held_s: float = Field(0.2, ge=0, description="a segment placed on three points alone, with no posed neighbour to "
                          "confirm it, stands once so placed at the same place in every frame this long")
    max_speed_mm_s: float = Field(3000.0, gt=0, description="fastest a segment moves, bounding where to look for it")
    velocity_smoothing: float = Field(0.7, gt=0, le=1, description="weight of the newest velocity in a marker's "
                                      "smoothed velocity")


@dataclass
class _Segment:
    markers: np.ndarray  # indices into the model's marker list
    local: np.ndarray  # (n, 3) layout in the segment's frame
    tol: np.ndarray  # (n,) largest distance between the fitted layout and a point each marker keeps (mm)
    # (other segment, centre in this frame, centre in the other's, largest distance between the centres the two put)
    joints: list[tuple[int, np.ndarray, np.ndarray, float]]

    def __post_init__(self) -> None:
        self.sides = norm(self.local[:, None] - self.local[None])  # (n, n) the layout's distances
        self.slack = self.tol[:, None] + self.tol[None]  # (n, n) how far two points keeping them may stray
        rows, cols = np.triu_indices(len(self.local), 1)
        self.pair_sides, self.pair_slack = self.sides[rows, cols], self.slack[rows, cols]  # the same, once per pair


class Poses:
    """The segments' poses in one frame, as arrays for the compiled steps: rotations ``rot`` (S, 3, 3), translations
    ``shift`` (S, 3) and whether posed, ``posed`` (S,); zero where not posed."""

    def __init__(self, segments: int) -> None:
        self.rot, self.shift = np.zeros((segments, 3, 3)), np.zeros((segments, 3))
        self.posed = np.zeros(segments, np.bool_)

    def set(self, s: int, rot: np.ndarray, shift: np.ndarray) -> None:
        """Pose segment ``s``."""
        self.rot[s], self.shift[s], self.posed[s] = rot, shift, True

    def clear(self, s: int) -> None:
        """Segment ``s`` has no pose."""
        self.rot[s], self.shift[s], self.posed[s] = 0.0, 0.0, False

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``rot``, ``shift`` and ``posed``: the arrays themselves, which the compiled steps pose segments in."""
        return self.rot, self.shift, self.posed


class ModelLabeller:
    """Streaming labeller that names points with a skeleton's marker names; feed frames in time order to
    :meth:`update`. ``labels`` are the skeleton's markers that have a layout, in the skeleton's order."""

    def __init__(self, skeleton: SkeletonModel, rate: float, config: ModelLabellerConfig | None = None) -> None:
        if rate <= 0:
            raise ValueError("rate must be positive")
        self.config = config or ModelLabellerConfig()
        self.rate = float(rate)
        # the widest gate of a followed marker at this rate (``labeller.own_gates`` gives each its own)
        self._widest = frame_gate(self.config.follow_mm, self.config.frame_accel_mm_s2, self.rate)
        self.labels: list[str] = []
        self.segments: list[_Segment] = []
        index: dict[str, int] = {}
        self._snug: dict[tuple[int, int], float] = {}  # per joint (both ways), see below
        # per joint (both ways): each segment's rotation relative to the other as they mostly stood in calibration
        self._calibrated: dict[tuple[int, int], np.ndarray] = {}
        for seg in skeleton.segments:
            if seg.marker_offsets is None or len(seg.markers) == 0:
                continue
            first = len(self.labels)
            self.labels += seg.markers
            index[seg.name] = len(self.segments)
            spread = np.zeros(len(seg.markers)) if seg.marker_spread_mm is None else np.array(seg.marker_spread_mm)
            tol = np.maximum(self.config.fit_mm, self.config.spread_sigmas * spread)
            self.segments.append(_Segment(np.arange(first, len(self.labels)), np.array(seg.marker_offsets, float),
                                          tol, []))
        if not self.segments:
            raise ValueError(f"skeleton {skeleton.name!r} has no segment with a marker layout")
        if len(set(self.labels)) != len(self.labels):
            raise ValueError(f"skeleton {skeleton.name!r} names a marker on two segments")
        for joint in skeleton.joints:
            if joint.parent in index and joint.child in index and joint.parent_offset and joint.child_offset:
                p, c = index[joint.parent], index[joint.child]
                po, co = np.array(joint.parent_offset), np.array(joint.child_offset)
                held = max(self.config.joint_mm, self.config.spread_sigmas * (joint.gap_mm or 0.0))
                # how far apart the two put the centre at most, as far as calibration saw
                self._snug[p, c] = self._snug[c, p] = max(self.config.fit_mm,
                                                          self.config.spread_sigmas * (joint.gap_mm or 0.0))
                self.segments[p].joints.append((c, po, co, held))
                self.segments[c].joints.append((p, co, po, held))
                if joint.posture is not None:
                    self._calibrated[c, p] = Rotation.from_rotvec(np.radians(joint.posture)).as_matrix()
                    self._calibrated[p, c] = self._calibrated[c, p].T
        n = len(self.labels)
        # the segments as arrays, for their compiled steps; per marker, its tolerance (see _Segment.tol)
        self._tables = Tables.of(self.segments)
        self._tol = self._tables.tol
        self._segment_of = np.empty(n, np.intp)  # per marker: its segment
        for s, one in enumerate(self.segments):
            self._segment_of[one.markers] = s
        # a marker's weight in a fit: 1 for one no looser than fit_mm, less for one known to stray
        self._weight = (self.config.fit_mm / self._tol) ** 2
        # per joint of each segment (as ``Tables``), its weight in a fit
        self._joint_w = np.array([self._joint_weight(tol) for tol in self._tables.joint_tol], np.float64)
        self._look_alikes = _look_alikes(self.segments)
        self.pos = np.full((n, 3), np.nan)
        self.vel = np.zeros((n, 3))
        self.last = np.full(n, -np.inf)
        self.streak = np.zeros(n, np.int64)
        self.pose = Poses(len(self.segments))  # the last frame's
        # how surely each segment was posed this frame: 0 by three markers or more, 1 through joints, 2 with a turn
        # left to its previous pose, or out of reach (``_search``) (3: not posed)
        self._level = np.full(len(self.segments), 3)
        self._last_seen = np.full((len(self.segments), 3), np.nan)  # where each segment was last posed
        self._last_time = np.full(len(self.segments), -np.inf)
        # each segment's rotation relative to each neighbour (S, S, 3, 3), when both were last surely posed: its
        # posture there, where known (S, S)
        self._posture = np.zeros((len(self.segments), len(self.segments), 3, 3))
        self._posture_known = np.zeros((len(self.segments), len(self.segments)), np.bool_)
        # per segment placed on three points alone with no posed neighbour: since when so placed in every frame, and
        # where in the last
        self._doubted_since = np.full(len(self.segments), np.nan)
        self._doubted_at = np.full((len(self.segments), 3), np.nan)
        self._time = -np.inf

    @property
    def time(self) -> float:
        """Capture time of the last frame named (s; -inf before the first)."""
        return self._time

    @property
    def posed(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The last frame's poses as arrays (``Poses.arrays``): rotations, translations and whether posed."""
        return self.pose.arrays()

    def update(self, points: np.ndarray, time: float) -> tuple[np.ndarray, np.ndarray]:
        """Name one frame of points ``(M, 3)`` (NaN rows ignored) captured at ``time`` seconds (increasing).

        Returns the markers' positions ``(N, 3)`` in ``labels`` order (NaN where unseen) and the marker of each row
        of ``points`` (-1 for none).
        """
        cfg = self.config
        if time <= self._time:
            raise ValueError(f"frame times must increase: {time} after {self._time}")
        dt_frame, self._time = time - self._time, time
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        rows = np.flatnonzero(np.isfinite(pts).all(axis=1))
        z = pts[rows]
        taken = np.full(len(z), -1, np.intp)
        cur = np.full((len(self.labels), 3), np.nan)
        refused = np.zeros((len(self.labels), len(z)), bool)  # per marker, the points a fit gave back this frame
        # 1. markers seen in the previous frame follow their points
        live = np.flatnonzero(self.streak > 0)
        dt = time - self.last[live]
        follow = own_gates(cfg.follow_mm, self._widest, self.vel[live], dt)
        ti, pi = assign(self.pos[live] + self.vel[live] * dt[:, None], follow, z)
        cur[live[ti]], taken[pi] = z[pi], live[ti]
        poses = Poses(len(self.segments))
        # per segment: its anchors, look-alikes and reaches at its last search
        searched: dict[int, tuple[int, bool, int]] = {}
        # segments found this frame on three points alone, for want of a look-alike, or out of reach (``_search``):
        # whether a neighbour may confirm each
        seeds: dict[int, bool] = {}
        self._level[:] = 3
        while True:
            posed = self._pose_segments(poses, cur, taken, refused)
            self._take_predicted(poses, cur, taken, z, time, refused)
            found = self._search(poses, cur, taken, z, searched, seeds)
            if not (posed or found or self._search_pairs(poses, cur, taken, z)
                    or self._challenge(poses, cur, taken, z)):
                break
        doubted = np.zeros(len(self.segments), bool)
        for s, confirmable in seeds.items():
            if not (confirmable and self._confirmed(s, poses)) and not self._held(s, poses, dt_frame, doubted):
                self._give_back(self.segments[s].markers, cur, taken, refused)
                poses.clear(s)
                self._level[s] = 3
        self._doubted_since[~doubted] = np.nan
        self._observe(cur, time)
        self.pose = poses
        rot, shift, standing = self.posed
        sure = standing & (self._level < 2)
        self._last_seen[sure], self._last_time[sure] = shift[sure], time
        _remember_postures(rot, sure, self._tables.joint_first, self._tables.other, self._posture, self._posture_known)
        point_marker = np.full(len(pts), -1, np.intp)
        point_marker[rows] = taken
        return cur, point_marker

    def _pose_segments(self, poses: Poses, cur: np.ndarray, taken: np.ndarray, refused: np.ndarray) -> bool:
        """Fit every segment not posed yet whose markers, joint centres and previous pose fix a pose, surest first:
        three markers or more, then three points with joint centres, then two with the previous pose
        (``_pose_by_markers``, compiled). A marker far from its fitted place gives its point back (as ``_give_back``).
        True when a segment was posed."""
        rot, shift, posed = poses.arrays()  # posed in place
        before_rot, before_shift, before = self.posed
        tables = self._tables
        if not _pose_by_markers(cur, taken, refused, self.streak, rot, shift, posed, self._level, before_rot,
                                before_shift, before, self._posture, self._posture_known, tables.first, tables.count,
                                tables.local, tables.tol, self._weight, tables.joint_first, tables.other, tables.here,
                                tables.there, tables.joint_tol, self._joint_w):
            return False
        return True

    def _marked(self, markers: np.ndarray) -> np.ndarray:
        """Per marker, whether it is one of ``markers``, and one more entry, False, that -1 (none) indexes."""
        mask = np.zeros(len(self.labels) + 1, np.bool_)
        mask[markers] = True
        return mask

    def _among(self, taken: np.ndarray, markers: np.ndarray) -> np.ndarray:
        """Whether each of ``taken`` (markers, -1 for none) is one of ``markers``: ``np.isin``, without its sort."""
        return self._marked(markers)[taken]

    def _matched(self, cur: np.ndarray) -> np.ndarray:
        """Per segment, how many of its markers are matched (``cur`` finite)."""
        return np.bincount(self._segment_of[np.isfinite(cur[:, 0])], minlength=len(self.segments))

    def _give_back(self, markers: np.ndarray, cur: np.ndarray, taken: np.ndarray, refused: np.ndarray) -> None:
        """Unmatch ``markers``: their points are free again, but not to them (``refused``) until the next frame."""
        _give_back_marked(self._marked(markers), cur, taken, refused, self.streak)

    def _joint_weight(self, tol: float) -> float:
        """A joint centre's weight in a fit: ``JOINT_WEIGHT``, less for a joint known to gape (as for a marker)."""
        return JOINT_WEIGHT * (self.config.joint_mm / tol) ** 2

    def _take_predicted(self, poses: Poses, cur: np.ndarray, taken: np.ndarray, z: np.ndarray, time: float,
                        refused: np.ndarray) -> None:
        """Give the points left over to the unmatched markers predicted by their segment's pose, or, for a segment
        with no pose, by a short constant-velocity coast.

        A segment posed through its joints, or from two points and its previous pose, may be turned some way from
        the fit: its markers take a point within ``weak_gate_mm`` of the prediction, but only one keeping the
        layout's distances to the segment's markers seen now (within ``fit_mm``) and to its joint centres (within
        each joint's tolerance, ``joint_mm`` or wider), and only where neither the point nor the marker has another
        such candidate. No marker takes a point its segment's fit gave back from it this frame (``refused``).
        """
        cfg = self.config
        rot, shift, posed = poses.arrays()
        self._reclaim(rot, shift, posed, cur, taken, z, refused)
        tables = self._tables
        markers, free, cost = _predicted_costs(cur, taken, z, refused, time, rot, shift, posed, self._level,
                                               self._segment_of, tables.first, tables.count, tables.local,
                                               self._tol, tables.joint_first, tables.other, tables.here,
                                               tables.there, tables.joint_tol, self.pos, self.vel, self.last,
                                               cfg.gate_mm, cfg.fit_mm, cfg.weak_gate_mm, cfg.max_coast_s)
        mi, fi = match(cost)
        cur[markers[mi]] = z[free[fi]]
        taken[free[fi]] = markers[mi]

    def _predicted(self, markers: np.ndarray, rot: np.ndarray, shift: np.ndarray,
                   posed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where each of ``markers`` lies by its segment's pose (``Poses.arrays``) ``(M, 3)``, NaN where its segment has
        none, and its gate (M,): ``gate_mm``, widened by as much as the marker's tolerance exceeds ``fit_mm`` where
        posed."""
        pred, gate = np.full((len(markers), 3), np.nan), np.full(len(markers), self.config.gate_mm)
        _predict(markers, rot, shift, posed, self._segment_of, self._tables.local, self._tol, self.config.fit_mm, pred,
                 gate)
        return pred, gate

    def _reclaim(self, rot: np.ndarray, shift: np.ndarray, posed: np.ndarray, cur: np.ndarray, taken: np.ndarray,
                 z: np.ndarray, refused: np.ndarray) -> None:
        """Give the unmatched markers of segments posed by three markers or more (the poses as ``Poses.arrays``) the
        points where their poses put them (within ``gate_mm``, as step 3) that markers of segments with no pose hold:
        such a marker only followed its point from frame to frame, and once it had taken another marker's, nothing else
        would take it back. The marker that held the point gives it back (``_give_back``)."""
        level = self._level[self._segment_of]  # per marker: how its segment was posed (3: not)
        missing = np.flatnonzero(np.isnan(cur[:, 0]) & (level == 0))
        if not len(missing):
            return
        held = np.flatnonzero((taken >= 0) & (level[np.maximum(taken, 0)] == 3))
        if not len(held):
            return
        pred, gate = self._predicted(missing, rot, shift, posed)
        cost = np.where(refused[np.ix_(missing, held)], 0.0, gated_cost(pred, gate, z[held]))
        mi, hi = match(cost)
        if not len(mi):
            return
        self._give_back(taken[held[hi]], cur, taken, refused)
        cur[missing[mi]] = z[held[hi]]
        taken[held[hi]] = missing[mi]

    def _search(self, poses: Poses, cur: np.ndarray, taken: np.ndarray, z: np.ndarray, searched: dict,
                seeds: dict[int, bool]) -> bool:
        """Look for each segment with no pose among the points left over and those of its own markers matched so far
        by its layout (``_place_layout``), its joint centres to surely posed segments kept within their tolerance;
        True when one was placed. A segment is searched again in a frame only when more of its neighbours got posed, or
        its look-alikes did, or more segments it reaches (``_reaches``).
        A segment with joints placed on its three points for want of a look-alike elsewhere (``alone``), with no joint
        centre to hold it and not near where it was lately, is added to ``seeds``: any three points at its layout's
        distances fit it, a chance triangle across two segments of another limb among them when its own markers are
        hidden, so it stands only if a neighbour is posed at their joint in the same frame (``_confirmed``), or, no
        neighbour posed, once so placed for a while (``_held``).
        A segment with no sure neighbour and no pose lately whose placement puts a joint centre farther from a surely
        posed segment than the segments between them reach (``_reaches``: at a cold start, the other leg's thigh on a
        triangle of shoulder and upper arm) is weakly posed (level 2: no neighbour is placed through its joints) and
        added to ``seeds`` as one no neighbour confirms: it stands only once so placed for a while.
        A segment of two markers as far from its joint (a foot's toe and fifth metatarsal, each 122 mm from the ankle)
        fits its points both ways round, and no posture to its neighbour tells the two apart until it has been posed
        once: until then, the posture it mostly had to that neighbour in calibration does (``Joint.posture``). Not for
        larger segments, which a live posture soon serves, and which a calibration that did not cover the capture's
        postures would mirror."""
        cfg = self.config
        placed = False
        for s, seg in enumerate(self.segments):
            if poses.posed[s]:
                continue
            sure = [(other, here, there, tol) for other, here, there, tol in seg.joints
                    if self._sure(other, poses)]
            alone = self._alone(s, poses)
            dt = self._time - self._last_time[s]
            reaches = [] if sure or dt <= cfg.recent_s else self._reaches(s, poses)
            if searched.get(s, (-1, False, -1)) >= (len(sure), alone, len(reaches)):
                continue
            searched[s] = (len(sure), alone, len(reaches))
            anchors = [(here, poses.rot[other] @ there + poses.shift[other], tol, self._joint_weight(tol))
                       for other, here, there, tol in sure]
            posture = [poses.rot[other] @ self._posture[s, other] for other, *_ in sure
                       if self._posture_known[s, other]]
            free = np.flatnonzero((taken < 0) | self._among(taken, seg.markers))  # its markers matched so far may move
            if not len(free):
                continue
            around = (self._last_seen[s], 100.0 + cfg.max_speed_mm_s * dt) if dt <= cfg.recent_s else None
            prior = [poses.rot[other] @ self._calibrated[s, other] for other, *_ in sure
                     if (s, other) in self._calibrated] if len(seg.markers) == 2 and not posture else []
            best = _place_layout(seg.local, z[free], seg.tol, self._weight[seg.markers], anchors, around, posture,
                                 alone, prior=prior)
            if best is None:
                continue
            points = {slot: int(free[p]) for slot, p in best[0].items()}
            beyond = any(np.linalg.norm(best[1] @ here + best[2] - world) > far for here, world, far in reaches)
            self._place(s, points, best[1], best[2], 2 if beyond else 1 if anchors else 0, poses, cur, taken, z)
            if beyond or (alone and not anchors and around is None and seg.joints):
                seeds[s] = not beyond
            placed = True
        return placed

    def _reaches(self, s: int, poses: Poses) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """How far each joint centre of segment ``s`` may lie from the joint centres of the surely posed segments
        reached from it through segments with no sure pose: per such pair, the centre in ``s``'s frame, the other's in
        the world, and the largest distance between them (mm): the sum, over the segments between, of the distance
        between each one's two joint centres (fixed, as the segment is rigid), widened by every joint's tolerance."""
        reaches = []
        for first, here, entry, tol in self.segments[s].joints:
            if self._sure(first, poses):
                continue
            visited = {s, first}
            # a segment between, where the way in lies in its frame, the lengths and the tolerances so far
            walk = [(first, entry, 0.0, tol)]
            while walk:
                m, entry, length, slack = walk.pop()
                for other, centre, there, joint_tol in self.segments[m].joints:
                    if other in visited:
                        continue
                    visited.add(other)
                    far, loose = length + float(np.linalg.norm(centre - entry)), slack + joint_tol
                    if self._sure(other, poses):
                        reaches.append((here, poses.rot[other] @ there + poses.shift[other], far + loose))
                    else:
                        walk.append((other, there, far, loose))
        return reaches

    def _challenge(self, poses: Poses, cur: np.ndarray, taken: np.ndarray, z: np.ndarray) -> bool:
        """Place anew each segment posed by three of its markers or more where its layout lands on more points, among
        the points left over and its own, its joint centres to segments so posed kept within their tolerances, when
        that placement is clearly best (``_place_layout``). A segment placed on chance points (at a cold start, three
        of another segment's) is followed on them while its own markers go unmatched: where they show, it is found
        again. True when one was placed."""
        moved = False
        count = self._matched(cur)
        for s in np.flatnonzero((self._level == 0) & (count < self._tables.count)).tolist():
            left = np.flatnonzero(taken < 0)
            if not len(left):
                break  # its own points alone land no more than it has
            seg, have = self.segments[s], int(count[s])
            free = np.concatenate([left, np.flatnonzero(self._among(taken, seg.markers))])
            free = free[could_hold(seg, z[free], have + 1)]
            if len(free) <= have:
                continue
            anchors = [(here, poses.rot[other] @ there + poses.shift[other], tol, self._joint_weight(tol))
                       for other, here, there, tol in seg.joints if self._level[other] == 0]
            best = _place_layout(seg.local, z[free], seg.tol, self._weight[seg.markers], anchors, least=have + 1)
            if best is None:
                continue
            points = {slot: int(free[p]) for slot, p in best[0].items()}
            self._place(s, points, best[1], best[2], 0, poses, cur, taken, z)
            moved = True
        return moved

    def _place(self, s: int, points: dict[int, int], rot: np.ndarray, shift: np.ndarray, level: int, poses: Poses,
               cur: np.ndarray, taken: np.ndarray, z: np.ndarray) -> None:
        """Pose segment ``s`` at ``level``, its markers matched to the points of ``z`` that ``points`` gives by
        layout row, instead of any matched before."""
        seg = self.segments[s]
        cur[seg.markers] = np.nan
        taken[self._among(taken, seg.markers)] = -1
        for slot, point in points.items():
            cur[seg.markers[slot]] = z[point]
            taken[point] = seg.markers[slot]
        poses.set(s, rot, shift)
        self._level[s] = level

    def _search_pairs(self, poses: Poses, cur: np.ndarray, taken: np.ndarray, z: np.ndarray) -> bool:
        """When nothing else poses a segment: place the first segment of three markers that has no pose, no surely
        posed neighbour, no pose lately and a look-alike with no pose (both feet unposed: a deadlock the ``alone``
        rule cannot break), together with a neighbour (``_pair``). True when one was placed."""
        for s, seg in enumerate(self.segments):
            if (poses.posed[s] or len(seg.markers) != 3 or self._time - self._last_time[s] <= self.config.recent_s
                    or any(self._sure(o, poses) for o, *_ in seg.joints) or self._alone(s, poses)):
                continue
            paired = self._pair(s, seg, poses, taken, z)
            if paired is not None:
                for one, (points, rot, shift) in paired.items():
                    self._place(one, points, rot, shift, 0 if one == s else 1, poses, cur, taken, z)
                return True
        return False

    def _pair(self, s: int, seg: _Segment, poses: Poses, taken: np.ndarray,
              z: np.ndarray) -> dict[int, tuple[dict[int, int], np.ndarray, np.ndarray]] | None:
        """Segment ``s`` placed on three points with a neighbour that has no pose either, placed on three or more of its
        own points (both, for a neighbour of two markers: a shank, its shin and ankle markers) and their joint centre
        (within the largest distance calibration saw between the centres the two put, or ``fit_mm``), when exactly one
        set of points for ``s`` lets a neighbour be placed so: per segment, its points by layout row (indices into
        ``z``), rotation and translation; else None.

        A triangle alone could be its look-alike's (a triangle fits its mirror image). Its joint centre tells: a
        layout placed on its mirror image's points puts the centre on the wrong side of their plane, where the
        neighbour's points do not lie."""
        hinged = [(o, here, there, self._snug[s, o]) for o, here, there, _ in seg.joints
                  if not poses.posed[o] and len(self.segments[o].markers) >= 2]
        if not hinged:
            return None
        free = np.flatnonzero((taken < 0) | self._among(taken, seg.markers))
        # per neighbour, the points it may take: free, or matched so far to it or to ``s``
        open_to = {o: (taken < 0) | self._among(taken, np.concatenate([seg.markers, self.segments[o].markers]))
                   for o, *_ in hinged}
        found: dict[frozenset, dict[int, tuple[dict[int, int], np.ndarray, np.ndarray]]] = {}
        for hits, _, rot, shift in zip(*_placements(seg.local, z[free], seg.tol, self._weight[seg.markers], [], 3),
                                       strict=True):
            points = {slot: int(free[p]) for slot, p in _landed(hits).items()}
            for o, here, there, tol in hinged:
                other = self.segments[o]
                rest = np.flatnonzero(open_to[o] & ~np.isin(np.arange(len(z)), list(points.values())))
                anchor = [(there, rot @ here + shift, tol, self._joint_weight(tol))]
                best = _place_layout(other.local, z[rest], other.tol, self._weight[other.markers], anchor)
                if best is not None and len(best[0]) >= min(3, len(other.markers)):
                    key = frozenset(points.items())
                    found.setdefault(key, {s: (points, rot, shift),
                                           o: ({slot: int(rest[p]) for slot, p in best[0].items()}, best[1], best[2])})
        return next(iter(found.values())) if len(found) == 1 else None

    def _sure(self, s: int, poses: Poses) -> bool:
        """Whether segment ``s`` is surely posed this frame: by three markers or more, or through joints."""
        return bool(poses.posed[s]) and self._level[s] < 2

    def _alone(self, s: int, poses: Poses) -> bool:
        """Whether three points, its whole layout, are segment ``s``'s alone: it has three markers and every segment
        with a triangle like its own is surely posed, its points accounted for."""
        return len(self.segments[s].markers) == 3 and all(self._sure(t, poses) for t in self._look_alikes[s])

    def _confirmed(self, s: int, poses: Poses) -> bool:
        """Whether a surely posed neighbour of segment ``s`` puts their joint centre where ``s``'s pose does, within
        the joint's tolerance."""
        rot, shift = poses.rot[s], poses.shift[s]
        return any(self._sure(other, poses)
                   and np.linalg.norm(rot @ here + shift - poses.rot[other] @ there - poses.shift[other]) <= tol
                   for other, here, there, tol in self.segments[s].joints)

    def _held(self, s: int, poses: Poses, dt: float, doubted: np.ndarray) -> bool:
        """Whether segment ``s``, placed on three points alone or out of reach (a seed, ``_search``) with no
        neighbour posed to confirm it, has been so placed in every frame for ``held_s``, each time within
        ``max_speed_mm_s`` of the frame before (plus ``fit_mm``): a chance triangle across two segments of another
        limb keeps the layout's distances only while that joint keeps still, where the segment's own markers keep them
        as it moves. Marks ``s`` in ``doubted``."""
        if any(poses.posed[other] for other, *_ in self.segments[s].joints):
            return False  # a neighbour posed elsewhere refutes it
        cfg = self.config
        shift = poses.shift[s]
        near = np.linalg.norm(shift - self._doubted_at[s]) <= cfg.max_speed_mm_s * dt + cfg.fit_mm
        if np.isnan(self._doubted_since[s]) or not near:  # not so placed in the frame before, or elsewhere
            self._doubted_since[s] = self._time
        self._doubted_at[s] = shift
        doubted[s] = True
        return self._time - self._doubted_since[s] >= cfg.held_s

    def sureness(self, marker: np.ndarray) -> np.ndarray:
        """How surely the last frame posed the segment of each of ``marker`` (a row's marker, -1 for none): 0 by three
        of its markers or more, 1 by its markers and joint centres, 2 by two points and its last pose, or out of reach
        of the posed segments (``_search``), 3 not at all (a marker only followed from frame to frame, or none)."""
        return np.where(marker >= 0, self._level[self._segment_of[np.maximum(marker, 0)]], 3)

    def _observe(self, cur: np.ndarray, time: float) -> None:
        """Take the markers matched this frame (``cur`` finite) as seen at ``time``: their positions, smoothed
        velocities and streaks (``observed``; a marker found again after a gap starts with no velocity)."""
        observed(cur, time, self.pos, self.vel, self.last, self.streak, self.config.velocity_smoothing, 0.0)


class TrackedModelLabeller:
    """Streaming labeller that names points with a skeleton's marker names and keeps a name with its point's track;
    feed frames in time order to :meth:`update`, as to :class:`ModelLabeller`.

    :class:`ModelLabeller` names a point only in the frames where its segment can be posed, and a segment it poses wrong
    keeps its wrong names while its markers are followed. The model-free labeller (``Labeller``) follows the same points
    as tracks, one marker each across most gaps, with no name. Each track counts the names its points were given, over
    its whole life and over its current run (the frames it has been seen in a row: one marker surely). A point then
    takes, the surest first and never a name another point of the frame took: its run's name (given to more than half of
    the run's points), else its track's (given to more than half of the named ones), else the name
    :class:`ModelLabeller` gave it, else the name its run's frames agree on (``RunningEvidence``: where no frame poses
    its segment). The same rules as over a whole recording (:func:`label_with_skeleton`), known only up to the current
    frame, but for two. A track's name stands only once the poses gave it in two frames or more: live, on the stress
    cases, a name they gave in one frame alone was a chance placement's; over a whole recording, the backward pass votes
    too. And a name given only because its marker followed the point, its segment not posed, is not counted: it echoes a
    name given before and is no new evidence (over a whole recording, leaving it out swung cases both ways). A run whose
    name the poses give for a while to another run, which they name so throughout, and its own point another name,
    starts afresh (``_tally``), and so does a run whose name only a segment not posed by its markers backs, its point
    named otherwise by one so posed."""

    def __init__(self, skeleton: SkeletonModel, rate: float, config: ModelLabellerConfig | None = None) -> None:
        self.model = ModelLabeller(skeleton, rate, config)
        self.tracks = Labeller(LabellerConfig(), rate)
        self.rate = self.model.rate
        self.labels = self.model.labels
        markers = len(self.labels)
        self._votes = np.zeros((0, markers), np.int64)  # per track: the names its points were given
        self._run = np.zeros((0, markers), np.int64)  # per track: the same over its current run
        self._run_length = np.zeros(0, np.int64)
        self._seen = np.zeros(0, bool)  # per track: seen in the last frame
        self._contested = np.zeros(0, np.int64)  # per track: frames in a row another run took its run's name
        self._evidence = RunningEvidence(self.model.segments, self.model._snug, self.rate, self.model.config.joint_mm)
        self._by_evidence = np.zeros(0, np.intp)  # per track: the name its run's evidence gave it, -1 for none

    @property
    def time(self) -> float:
        """Capture time of the last frame named (s; -inf before the first)."""
        return self.model.time

    def update(self, points: np.ndarray, time: float) -> tuple[np.ndarray, np.ndarray]:
        """Name one frame of points ``(M, 3)`` (NaN rows ignored) captured at ``time`` seconds (increasing): the
        markers' positions ``(N, 3)`` in ``labels`` order (NaN where unseen) and the marker of each row of
        ``points`` (-1 for none)."""
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        _, given = self.model.update(pts, time)
        point_track = self.tracks.update(pts, time).point_track
        grow = len(self.tracks.labels) - len(self._seen)
        if grow > 0:
            self._votes = np.vstack([self._votes, np.zeros((grow, len(self.labels)), np.int64)])
            self._run = np.vstack([self._run, np.zeros((grow, len(self.labels)), np.int64)])
            self._run_length = np.concatenate([self._run_length, np.zeros(grow, np.int64)])
            self._seen = np.concatenate([self._seen, np.zeros(grow, bool)])
            self._contested = np.concatenate([self._contested, np.zeros(grow, np.int64)])
            self._by_evidence = np.concatenate([self._by_evidence, np.full(grow, -1, np.intp)])
            self._evidence.grow(len(self._seen))
        level = self.model._level[self.model._segment_of]  # per marker: how its segment was posed (3: not)
        marker = np.full(len(pts), -1, np.intp)
        held = np.zeros(len(self.labels), np.bool_)
        fresh = np.empty(len(pts), np.intp)
        restarted = _tally(point_track, given, level, self._votes, self._run, self._run_length, self._seen,
                           self._contested, self._by_evidence, self.tracks.config.confirm_frames, marker, held, fresh)
        self._evidence.restart(fresh[:restarted])
        self._name_by_evidence(pts, point_track, marker, held)
        return self._named(pts, marker), marker

    def _name_by_evidence(self, pts: np.ndarray, point_track: np.ndarray, marker: np.ndarray, held: np.ndarray) -> None:
        """Name the tracked points left unnamed (``marker`` -1) by their runs' evidence (``RunningEvidence``), which
        this frame adds to: a run keeps the name its evidence gave it while no other point holds the name and the
        checks do not refute it; the others take the name the evidence now gives them, by their distances to what is
        known of the marker's segment, else three together as a segment none of whose markers is named."""
        rows = np.flatnonzero((marker < 0) & (point_track >= 0))
        if not len(rows):
            return
        tracks = point_track[rows]
        kept = self._by_evidence[tracks]
        for row, name in zip(rows[kept >= 0], kept[kept >= 0], strict=True):
            if not held[name]:
                marker[row] = name
                held[name] = True
        self._evidence.add(pts[rows], tracks, self._named(pts, marker), *self.model.posed, self.model._level)
        refuted = (kept >= 0) & self._evidence.refuted(tracks)[np.arange(len(tracks)), np.maximum(kept, 0)]
        self._by_evidence[tracks[refuted]] = -1
        dropped = refuted & (marker[rows] == kept)  # the name the run kept this frame, now refuted
        marker[rows[dropped]] = -1
        held[kept[dropped]] = False
        left = marker[rows] < 0
        names = self._evidence.names(tracks[left], ~held)
        for row, name in zip(rows[left][names >= 0], names[names >= 0], strict=True):
            marker[row] = name
            held[name] = True
            self._by_evidence[point_track[row]] = name
        rest = rows[marker[rows] < 0]
        for i, name in self._evidence.layouts(pts[rest], point_track[rest], self._named(pts, marker), ~held):
            marker[rest[i]] = name
            held[name] = True
            self._by_evidence[point_track[rest[i]]] = name

    def _named(self, pts: np.ndarray, marker: np.ndarray) -> np.ndarray:
        """Each marker's position (N, 3) from the points named it (``marker`` per point, -1 for none); NaN where none
        is."""
        named = np.full((len(self.labels), 3), np.nan)
        found = np.flatnonzero(marker >= 0)
        named[marker[found]] = pts[found]
        return named


@njit(cache=True)
def _tally(point_track: np.ndarray, given: np.ndarray, level: np.ndarray, votes: np.ndarray, run: np.ndarray,
           run_length: np.ndarray, seen: np.ndarray, contested: np.ndarray, by_evidence: np.ndarray, confirm: int,
           marker: np.ndarray, held: np.ndarray, fresh: np.ndarray) -> int:  # pragma: no cover
    """One frame of ``TrackedModelLabeller``'s bookkeeping, compiled: each point's track (``point_track``, -1 for
    none) counts the name the poses gave the point (``given``, by ``level``, per marker how its segment was posed),
    over its life (``votes``) and its run (``run``, ``run_length``), the state changed in place; the tracks not seen
    in the last frame (``seen``) start a run, and so do contested runs (below); then the points take names into
    ``marker`` (-1 given) and ``held`` (False given): by their runs, their tracks, then as the poses named them. The
    tracks that started a run are written to ``fresh``; their count is returned.

    A run starts afresh when the poses have given its name, ``confirm`` frames in a row, to the point of a run that
    claims it too and that they have named so in every frame of it, and its own point another name. Such a run took
    its name while its segment was posed wrong (a mate hidden, the layout fitted one marker over), and the marker
    whose name it is has come back: without this, the run's votes would hold the name as long as the run lasts, and
    that marker would go unnamed. So does a run whose name's segment is not posed by three of its markers or more
    while one so posed names its point otherwise, ``confirm`` frames in a row: its name rests on a marker that only
    followed the point, or on a looser pose. Any other run the poses name otherwise for a while keeps its name (a
    segment posed wrong for a moment)."""
    markers = votes.shape[1]
    rows = np.flatnonzero(point_track >= 0)
    n = len(rows)
    track = point_track[rows]
    restarted = 0
    for i in range(n):
        t = track[i]
        if not seen[t]:
            run[t, :] = 0
            run_length[t], contested[t], by_evidence[t] = 0, 0, -1
            fresh[restarted] = t
            restarted += 1
    seen[:] = False
    for i in range(n):
        t, name = track[i], given[rows[i]]
        seen[t] = True
        if name >= 0 and level[name] < 3:  # the names the poses gave, not those of markers only followed
            votes[t, name] += 1
            run[t, name] += 1
        run_length[t] += 1
    # contested runs
    claim = np.full(n, -1, np.intp)
    backed = np.zeros(markers, np.int64)  # per name: runs claiming it, named so in every frame
    for i in range(n):
        t = track[i]
        top, best = _most(run[t])
        if 2 * top > run_length[t]:
            claim[i] = best
        whole = top == run_length[t]  # the poses named every point of the run so
        if claim[i] >= 0 and given[rows[i]] == claim[i] and whole:
            backed[claim[i]] += 1
    for i in range(n):
        t, name, own = track[i], given[rows[i]], claim[i]
        if own >= 0 and name >= 0 and name != own and (backed[own] > 0 or (level[name] == 0 and level[own] != 0)):
            contested[t] += 1
        else:
            contested[t] = 0
        if contested[t] >= confirm:  # the run starts at this frame, with its name in it
            run[t, :] = 0
            run[t, name] = 1
            run_length[t], contested[t] = 1, 0
    # names: the runs', the tracks', then the poses'
    own_name, own_votes = np.empty(n, np.intp), np.empty(n, np.int64)
    usual_name, usual_votes = np.empty(n, np.intp), np.empty(n, np.int64)
    own_sure, usual_sure = np.empty(n, np.bool_), np.empty(n, np.bool_)
    for i in range(n):
        t = track[i]
        own_votes[i], own_name[i] = _most(run[t])
        usual_votes[i], usual_name[i] = _most(votes[t])
        own_sure[i] = 2 * own_votes[i] > run_length[t]
        usual_sure[i] = usual_votes[i] > 1 and 2 * usual_votes[i] > votes[t].sum()
    for choice, count, sure in ((own_name, own_votes, own_sure), (usual_name, usual_votes, usual_sure)):
        for i in _descending(count):
            row, name = rows[i], choice[i]
            if sure[i] and marker[row] < 0 and not held[name]:
                marker[row] = name
                held[name] = True
    for row in range(len(given)):
        if marker[row] < 0 and given[row] >= 0 and not held[given[row]]:
            marker[row] = given[row]
            held[given[row]] = True
    return restarted


@njit(cache=True)
def _most(counts: np.ndarray) -> tuple[int, int]:  # pragma: no cover
    """The largest of ``counts`` (0 for none) and its first index."""
    top, best = 0, 0
    for k in range(len(counts)):
        if counts[k] > top:
            top, best = counts[k], k
    return top, best


@njit(cache=True)
def _descending(count: np.ndarray) -> np.ndarray:  # pragma: no cover
    """The indices of ``count`` ordered by it, largest first, ties in index order (a stable sort)."""
    order = np.arange(len(count))
    for i in range(1, len(order)):
        k, j = order[i], i
        while j > 0 and count[order[j - 1]] < count[k]:
            order[j] = order[j - 1]
            j -= 1
        order[j] = k
    return order


def _place_layout(layout: np.ndarray, cloud: np.ndarray, tol: np.ndarray, weight: np.ndarray,
                  anchors: list[tuple[np.ndarray, np.ndarray, float, float]],
                  around: tuple[np.ndarray, float] | None = None, posture: list[np.ndarray] | None = None,
                  alone: bool = False,
                  least: int | None = None, prior: list[np.ndarray] | None = None,
                  ) -> tuple[dict[int, int], np.ndarray, np.ndarray] | None:
    """The placement of a segment's layout ``(n, 3)`` on ``cloud`` that fits clearly better than any other (more
    points, or a third of the misfit): the points it lands on by layout row, its rotation and translation; None when
    no placement is that sure. ``tol`` and ``weight`` (n,) are each layout point's tolerance (mm) and weight in the
    fit; two layout points keep their distance within the larger of their tolerances.

    With ``anchors`` (joint centres to posed segments: local, world, tolerance, weight in the fit), a placement lands
    two or more layout points on cloud points (within ``tol``) and every anchor within its tolerance of its world
    position. Without, it must land four or more: any three points form a triangle that also fits the mirror-image
    segment of the other side of the body, whose own markers may be the ones hidden now; three are enough when the
    segment's centre must lie ``around`` (centre, radius) where it was lately, or when it is ``alone``: a segment of
    three markers whose look-alikes (``_look_alikes``), which could take those points, are all surely posed.

    ``least``, when given, is the fewest layout points a placement must land instead.

    Placements that fit equally well (a symmetric layout: two markers at the same distances from the third and from
    the joint, each hidden in turn) are told apart by ``posture``: the rotations the segment would have if it kept,
    to each anchoring neighbour, the relative rotation it last had. The placement turned least from them is taken
    when every rival is turned at least ``POSTURE_DEG`` more; a joint does not flip a segment over between two
    sightings. With no ``posture``, ``prior`` (rotations as ``posture``, from the mean postures of calibration) tells
    apart, in the same way, only rivals that land on the same points: a placement and its mirror image.
    """
    if least is None:
        least = (4 if around is None and not alone else 3) if not anchors else 2 if len(anchors) == 1 else 1
    hits, misfit, rot, shift = _placements(layout, cloud, tol, weight, anchors, least, around)
    if not len(hits):
        return None
    landed = (hits >= 0).sum(axis=1)
    ranked = np.lexsort((misfit, -landed))  # most points first, then least misfit; a stable sort
    top = int(ranked[0])
    rivals = [int(i) for i in ranked if landed[i] == landed[top] and misfit[i] < 3.0 * misfit[top] + 1.0]
    if len(rivals) > 1:
        if not posture and len({frozenset(hits[i][hits[i] >= 0].tolist()) for i in rivals}) == 1:
            posture = prior
        if not posture:
            return None
        turn = sorted((np.mean([_angle(rot[i], expected) for expected in posture]), k) for k, i in enumerate(rivals))
        if turn[1][0] - turn[0][0] < POSTURE_DEG:
            return None
        top = rivals[turn[0][1]]
    return _landed(hits[top]), rot[top], shift[top]


def _placements(layout: np.ndarray, cloud: np.ndarray, tol: np.ndarray, weight: np.ndarray,
                anchors: list[tuple[np.ndarray, np.ndarray, float, float]], least: int,
                around: tuple[np.ndarray, float] | None = None,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every placement of a layout on ``cloud`` (arguments as for ``_place_layout``) that lands ``least`` layout
    points or more on distinct cloud points, each within its tolerance, with every anchor within its own: per
    placement, the cloud point each layout row lands on (-1 for none; ``_landed``), its RMS misfit (markers and
    anchors, mm), rotation and translation. The search is compiled (``_placed``): at a cold start, or with a third of
    the markers hidden, it runs many times a frame."""
    if len(layout) < least:
        return np.zeros((0, len(layout)), np.intp), np.zeros(0), np.zeros((0, 3, 3)), np.zeros((0, 3))
    local_a = np.array([a[0] for a in anchors], dtype=np.float64).reshape(-1, 3)
    world_a = np.array([a[1] for a in anchors], dtype=np.float64).reshape(-1, 3)
    joint_tol = np.array([a[2] for a in anchors], dtype=np.float64)
    joint_weight = np.array([a[3] for a in anchors], dtype=np.float64)
    centre, reach = (np.full(3, np.nan), -1.0) if around is None else (np.asarray(around[0], np.float64),
                                                                         float(around[1]))
    return _placed(np.ascontiguousarray(layout, np.float64), np.ascontiguousarray(cloud, np.float64),
                   np.asarray(tol, np.float64), np.asarray(weight, np.float64), local_a, world_a, joint_tol,
                   joint_weight, least, centre, reach)


def _landed(hits: np.ndarray) -> dict[int, int]:
    """A placement's cloud point per layout row it lands (``_placements``' hits, -1 for none)."""
    return {int(r): int(hits[r]) for r in np.flatnonzero(hits >= 0)}


@njit(cache=True)
def _distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # pragma: no cover
    """(len(a), len(b)) Euclidean distances between two point sets."""
    out = np.empty((len(a), len(b)))
    for i in range(len(a)):
        for j in range(len(b)):
            out[i, j] = distance(a[i], b[j])
    return out


@njit(cache=True)
def _placed(layout: np.ndarray, cloud: np.ndarray, tol: np.ndarray, weight: np.ndarray, local_a: np.ndarray,
            world_a: np.ndarray, joint_tol: np.ndarray, joint_weight: np.ndarray, least: int, centre: np.ndarray,
            reach: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """``_placements``, compiled: per placement found, the cloud point of each layout row (-1 for none), its misfit,
    rotation and translation, the best of each set of points landed on, in the order first found. Each placement
    starts from layout rows and cloud points that, with the anchors, make three points at the layout's distances
    (within the larger of the two rows' tolerances; to an anchor, within its ``joint_tol``): a marker with two
    anchors or more, two markers with one, three markers without. ``reach`` below 0: no ``around``."""
    n, m, k = len(layout), len(cloud), len(local_a)
    d_cloud, d_layout = _distances(cloud, cloud), _distances(layout, layout)
    d_anchor, d_local = _distances(cloud, world_a), _distances(layout, local_a)
    width = 3 - min(k, 2)
    # the starting rows and points, ``width`` of each per start, in the order searched
    count = 0
    buffer = np.empty((16, 2, 3), np.intp)
    for a in range(n):
        for b in range(a + 1, n) if width > 1 else range(a, a + 1):
            for c in range(b + 1, n) if width > 2 else range(b, b + 1):
                for i in range(m):
                    for j in range(m) if width > 1 else range(i, i + 1):
                        if width > 1 and not abs(d_cloud[i, j] - d_layout[a, b]) < max(tol[a], tol[b]):
                            continue
                        for p in range(m) if width > 2 else range(j, j + 1):
                            if width > 2 and (p == i or p == j
                                              or not abs(d_cloud[i, p] - d_layout[a, c]) < max(tol[a], tol[c])
                                              or not abs(d_cloud[j, p] - d_layout[b, c]) < max(tol[b], tol[c])):
                                continue
                            rows, points = (a, b, c), (i, j, p)
                            good = True
                            for t in range(width if width < 3 else 0):  # each marker at its distances to the anchors
                                for q in range(k):
                                    if abs(d_anchor[points[t], q] - d_local[rows[t], q]) > joint_tol[q]:
                                        good = False
                            if not good:
                                continue
                            if count == len(buffer):
                                grown = np.empty((2 * count, 2, 3), np.intp)
                                grown[:count] = buffer
                                buffer = grown
                            for t in range(3):
                                buffer[count, 0, t], buffer[count, 1, t] = rows[t], points[t]
                            count += 1
    starts = buffer[:count]
    hits = np.full((max(count, 1), n), -1, np.intp)
    misfits, rots, shifts = np.empty(max(count, 1)), np.empty((max(count, 1), 3, 3)), np.empty((max(count, 1), 3))
    found = 0
    q = width + k
    here, there, w = np.empty((q, 3)), np.empty((q, 3)), np.empty(q)
    rot, shift = np.empty((3, 3)), np.empty(3)
    anchor_err, fit = np.empty(k), np.empty(n)
    hit, moved = np.empty(n, np.intp), np.empty(3)
    for start in range(count):
        for t in range(width):
            row, at = starts[start, 0, t], starts[start, 1, t]
            here[t], there[t], w[t] = layout[row], cloud[at], weight[row]
        for t in range(k):
            here[width + t], there[width + t], w[width + t] = local_a[t], world_a[t], joint_weight[t]
        if not kabsch_into(here, there, w / w.sum(), rot, shift):
            continue
        bad = False
        for t in range(k):
            place(rot, local_a[t], shift, moved)
            anchor_err[t] = distance(moved, world_a[t])
            bad |= anchor_err[t] > joint_tol[t]
        if bad or (reach >= 0 and distance(shift, centre) > reach):
            continue
        inside = 0
        for r in range(n):
            place(rot, layout[r], shift, moved)
            best, nearest = np.inf, -1
            for j in range(m):
                d = distance(moved, cloud[j])
                if d < best:
                    best, nearest = d, j
            fit[r] = best
            hit[r] = nearest if best < tol[r] else -1
            inside += best < tol[r]
        if inside < least:
            continue
        distinct = True
        for r in range(n):
            for r2 in range(r + 1, n):
                if hit[r] >= 0 and hit[r] == hit[r2]:
                    distinct = False
        if not distinct:
            continue
        # a joint known to gape counts its misfit as a marker counts a straying marker's: scaled down with its weight
        squares = 0.0
        for r in range(n):
            if hit[r] >= 0:
                squares += fit[r] ** 2
        anchor_misfit = 0.0
        for t in range(k):
            anchor_misfit += anchor_err[t] ** 2 * joint_weight[t] / JOINT_WEIGHT
        misfit = np.sqrt((squares + anchor_misfit) / (inside + k))
        same = -1
        for f in range(found):
            if (hits[f] == hit).all():
                same = f
        if same < 0:
            same, found = found, found + 1
        elif misfit >= misfits[same]:
            continue
        hits[same], misfits[same], rots[same], shifts[same] = hit, misfit, rot, shift
    return hits[:found], misfits[:found], rots[:found], shifts[:found]


def could_hold(seg: _Segment, cloud: np.ndarray, least: int) -> np.ndarray:
    """Which points of ``cloud`` could be among ``least`` of them that a placement of the segment's layout lands on:
    each such point lies at one of the layout's distances (within the two markers' tolerances together) from
    ``least - 1`` others of them. A quick bound before the search."""
    keep = np.ones(len(cloud), np.bool_)
    _keep_linked(np.ascontiguousarray(cloud, dtype=np.float64), seg.pair_sides, seg.pair_slack, least, keep)
    return keep


@njit(cache=True)
def _keep_linked(cloud: np.ndarray, sides: np.ndarray, slack: np.ndarray, least: int,
                 keep: np.ndarray) -> None:  # pragma: no cover
    """``could_hold`` into ``keep`` (all True given): the points linked (at one of ``sides`` within its ``slack``)
    to ``least - 1`` others kept, dropped round after round until none is dropped."""
    n = len(cloud)
    apart = _distances(cloud, cloud)
    linked = np.zeros((n, n), np.bool_)
    for a in range(n):
        for b in range(a, n):  # a point with itself too, as a layout's distances may be within their slack of 0
            for k in range(len(sides)):
                if abs(apart[a, b] - sides[k]) < slack[k]:
                    linked[a, b] = linked[b, a] = True
                    break
    dropped = True
    while dropped:
        dropped = False
        drop = np.zeros(n, np.bool_)
        for a in range(n):
            if keep[a]:
                links = 0
                for b in range(n):
                    links += linked[a, b] and keep[b]
                drop[a] = links < least - 1
                dropped = dropped or drop[a]
        for a in range(n):
            keep[a] = keep[a] and not drop[a]


def _look_alikes(segments: list[_Segment]) -> list[list[int]]:
    """For each segment, the others with three markers at the distances of three of its own (within the larger of
    the two markers' tolerances on each side): the segments whose points its layout could take when it is placed on
    three points alone. A triangle and its mirror image are alike, so the two sides' feet or hands are each other's;
    a segment of two markers has no triangle and no look-alike."""
    pairs = [[0, 0, 1], [1, 2, 2]]  # a triangle's sides, by its corners

    def triangles(seg: _Segment) -> tuple[np.ndarray, np.ndarray]:
        """The sides of every triangle of the layout, its corners in every order, and each side's tolerance."""
        corners = np.array(list(permutations(range(len(seg.local)), 3)), np.intp).reshape(-1, 3)
        sides = norm(seg.local[corners[:, pairs[0]]] - seg.local[corners[:, pairs[1]]])
        return sides, np.maximum(seg.tol[corners[:, pairs[0]]], seg.tol[corners[:, pairs[1]]])

    shapes = [triangles(seg) for seg in segments]
    out: list[list[int]] = [[] for _ in segments]
    for s, t in combinations(range(len(segments)), 2):
        (sides_s, tol_s), (sides_t, tol_t) = shapes[s], shapes[t]
        off = np.abs(sides_s[:, None] - sides_t[None])
        if (off <= np.maximum(tol_s[:, None], tol_t[None])).all(axis=2).any():
            out[s].append(t)
            out[t].append(s)
    return out


def _angle(rot: np.ndarray, other: np.ndarray) -> float:
    """The angle between two rotations, in degrees."""
    return float(np.degrees(np.arccos(np.clip((np.trace(rot.T @ other) - 1.0) / 2.0, -1.0, 1.0))))


def label_with_skeleton(frames: Sequence[np.ndarray] | np.ndarray, rate: float, skeleton: SkeletonModel,
                        config: ModelLabellerConfig | None = None,
                        report: Progress | None = None) -> tuple[np.ndarray, list[str]]:
    """Label a whole recording of point clouds with a skeleton's marker names: ``(F, N, 3)`` trajectories of its
    ``N`` markers (NaN where not found) and their names.

    The recording is labelled twice, forward and backward in time. A marker that comes back while its segment has no
    pose (a foot whose mates and shank are hidden) is left unnamed by the forward pass until the segment is found,
    and named by the backward pass, which met the segment posed first. A point takes the name of the pass that posed
    its segment more surely, the forward pass's where both did alike, a name going to one point of a frame
    (:func:`_merged`).

    Then the names go to whole trajectories: the recording is labelled without the skeleton too
    (:func:`label_sequence`), whose trajectories keep one marker each, however often their segment had no pose, and
    each run of a trajectory takes the name the passes gave most of its points, or its trajectory's
    (:func:`_track_names`). The parts of trajectories left unnamed take names where the frames along them agree, though
    no frame alone could pose their segment (:func:`name_by_evidence`: a leg whose two-marker segments are never seen
    whole). A point on no named run keeps its name from the passes. ``report`` is told each pass's progress.
    """
    forward = ModelLabeller(skeleton, rate, config)
    backward = ModelLabeller(skeleton, rate, config)
    n = len(frames)
    markers = len(forward.labels)
    clouds = [np.asarray(frames[f], dtype=float).reshape(-1, 3) for f in range(n)]
    ahead = [_pass(forward, points, i / rate) for i, points in enumerate(steps(clouds, n, "label forward", report))]
    behind = [_pass(backward, clouds[i], (n - 1 - i) / rate)
              for i in steps(range(n - 1, -1, -1), n, "label backward", report)][::-1]
    # per frame: each row's marker and how surely its segment was posed
    merged = [_merged(one, other) for one, other in zip(ahead, behind, strict=True)]
    named = [name for name, _ in merged]
    tracks, _ = label_sequence(steps(clouds, n, "label trajectories", report), rate, progress=report)
    track_row = np.array([source_rows(tracks[f], clouds[f]) for f in range(n)], np.intp).reshape(tracks.shape[:2])
    owner = name_by_evidence(tracks, _track_names(track_row, merged, markers), forward.segments, forward._snug, rate,
                             forward.config.joint_mm)
    out = np.full((n, markers, 3), np.nan)
    for f in range(n):
        rows = track_row[f]
        mine = np.flatnonzero(owner[f] >= 0)
        out[f, owner[f, mine]] = clouds[f][rows[mine]]
        free = np.ones(len(clouds[f]), bool)
        free[rows[mine]] = False
        left = np.flatnonzero(free & (named[f] >= 0))
        left = left[np.isnan(out[f, named[f][left], 0])]
        out[f, named[f][left]] = clouds[f][left]
    return out, list(forward.labels)


FOLLOWED_VOTE = 0.5
"""A point named by following alone (its segment not posed in that frame) counts this much of a vote towards its
trajectory's name, against a point named with its segment posed. Following from frame to frame can carry a name onto
another marker's point (in the stress benchmark's breakdance, a hip marker was followed as a shoulder marker for half a
second, while the backward pass posed the pelvis on it); a pose checks the name against the segment's layout."""


def _track_names(track_row: np.ndarray, named: list[tuple[np.ndarray, np.ndarray]], markers: int) -> np.ndarray:
    """The marker each trajectory's point is named, ``(F, T)`` (-1 for none), from the names each frame's rows were
    given and how surely (``_merged``), a point named by following alone counting ``FOLLOWED_VOTE``. A trajectory is
    named in runs: each run of frames it is seen in a row is one marker surely (followed from frame to frame), while
    across its gaps it may have been joined to another marker's.

    Each run first takes its trajectory's name: the name given most of the trajectory's points, if given to most of
    them; the trajectories with most votes first, and never a name to two runs that share a frame. A run whose own
    points were mostly given another name then takes that one, if no other run holds it in any of its frames: its
    trajectory was joined to it across a gap. The name it leaves is tried again by the runs it held back (a run of
    a trajectory that took another marker's points for a while holds that marker's name until it takes its own).
    Two runs that each hold, in frames they share, the name the other's points were mostly given trade names: two
    trajectories each joined across a gap to the other's marker (neither could take its own name first); where one
    of them is seen in several runs after that gap, they all trade with the other. Where the names of a whole segment
    were given turned (a layout that fits a quarter turn), the other runs of that segment hold them, and the
    trajectories' names stand."""
    frames, count = track_row.shape
    seen = track_row >= 0
    starts = run_starts(seen)
    # runs numbered trajectory by trajectory: a run's points follow its start in its trajectory's column
    run_of = np.where(seen, np.cumsum(starts.T.ravel()).reshape(count, frames).T - 1, -1)
    runs = int(starts.sum())
    length = np.bincount(run_of[seen], minlength=runs)
    track, first = np.nonzero(starts.T)  # each run's trajectory and first frame, in run order
    votes = np.zeros((runs, markers))
    weight = np.zeros(runs)
    for f in range(frames):
        k = np.flatnonzero(seen[f])
        name, level = named[f][0][track_row[f, k]], named[f][1][track_row[f, k]]
        w = np.where((level < 3) | (name < 0), 1.0, FOLLOWED_VOTE)  # a point named nothing counts whole
        np.add.at(weight, run_of[f, k], w)
        np.add.at(votes, (run_of[f, k[name >= 0]], name[name >= 0]), w[name >= 0])
    pooled = np.zeros((count, markers))
    np.add.at(pooled, track, votes)
    best = pooled.argmax(axis=1)
    top = pooled[np.arange(count), best]
    name_of = np.full(runs, -1, np.intp)
    holder = np.full((frames, markers), -1, np.intp)  # the run holding each name in each frame

    def drop(r: int) -> None:
        """Run ``r`` holds no name."""
        if name_of[r] >= 0:
            holder[first[r]:first[r] + length[r], name_of[r]] = -1
            name_of[r] = -1

    def give(r: int, m: int) -> bool:
        """Name run ``r`` marker ``m`` unless another run holds ``m`` in one of its frames; whether it was."""
        during = slice(first[r], first[r] + length[r])
        if ((holder[during, m] >= 0) & (holder[during, m] != r)).any():
            return False
        drop(r)
        name_of[r] = m
        holder[during, m] = r
        return True

    for k in np.argsort(-top, kind="stable"):
        if top[k] > 0 and 2 * top[k] > pooled[k].sum():
            for r in np.flatnonzero(track == k):
                give(int(r), int(best[k]))
    own = votes.argmax(axis=1)
    mostly = 2 * votes[np.arange(runs), own] > weight

    def trade(r: int) -> bool:
        """Run ``r`` takes its own name from the one run holding it in its frames, if that run's own name is the one
        ``r`` holds: they trade (neither could take its own first, the other holding it), and with ``r`` the other
        runs holding that name in the other run's frames whose own name is the other's; whether they did."""
        held = np.unique(holder[first[r]:first[r] + length[r], own[r]])
        held = held[(held >= 0) & (held != r)]
        if len(held) != 1 or not mostly[held[0]] or own[held[0]] != name_of[r]:
            return False
        q = int(held[0])
        mine, theirs = int(name_of[r]), int(name_of[q])
        # with r, the other runs holding ``mine`` in q's frames whose own name is ``theirs``: the rest of r's
        # trajectory, when it is seen in more than one run after the two trajectories were joined each to the other
        span = holder[first[q]:first[q] + length[q], mine]
        group = [r] + [int(p) for p in np.unique(span[span >= 0]) if p != r and mostly[p] and own[p] == theirs]
        for p in (*group, q):
            drop(p)
        if all([give(p, theirs) for p in group]) and give(q, mine):
            return True
        for p in (*group, q):  # a third run holds ``mine`` in q's frames, or ``theirs`` in one of theirs: as they were
            drop(p)
        for p in group:
            give(p, mine)
        give(q, theirs)
        return False

    given = True
    while given:  # a run taking its own name frees its trajectory's for a run it held back
        differs = sorted(np.flatnonzero(mostly & (own != name_of)), key=lambda r: -votes[r, own[r]])
        given = any([give(int(r), int(own[r])) for r in differs]) or any(trade(int(r)) for r in differs)
    return np.where(seen, name_of[np.maximum(run_of, 0)], -1)


def _pass(labeller: ModelLabeller, points: np.ndarray, time: float) -> tuple[np.ndarray, np.ndarray]:
    """One frame of a pass over a recording: the marker each row of ``points`` is named (-1 for none) and how surely
    its segment was posed (the labeller's level of that segment; 3 for a row named nothing)."""
    _, given = labeller.update(points, time)
    return given, labeller.sureness(given)


def _merged(one: tuple[np.ndarray, np.ndarray],
            other: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The marker each row is named (-1 for none) and how surely its segment was posed (3 for none), from two passes'
    names of the rows and how surely each name's segment was posed (``ModelLabeller`` levels: 0 by three of its
    markers or more, up to 3 followed only): each row takes the name of the pass that posed it more surely, the first
    pass's where both did alike, and a name goes to one row only, the surest claim first; a row whose claim another
    took keeps the other pass's name if it is free."""
    names, levels = np.concatenate([one[0], other[0]]), np.concatenate([one[1], other[1]])
    rows = np.concatenate([np.arange(len(one[0]))] * 2)
    out = np.full(len(one[0]), -1, np.intp)
    level = np.full(len(one[0]), 3, np.intp)
    held = np.zeros(max(int(names.max(initial=-1)) + 1, 0), bool)
    for k in np.lexsort((np.repeat([0, 1], len(one[0])), levels)).tolist():  # surest first, the first pass on ties
        if names[k] >= 0 and out[rows[k]] < 0 and not held[names[k]]:
            out[rows[k]] = names[k]
            level[rows[k]] = levels[k]
            held[names[k]] = True
    return out, level


@njit(cache=True)
def _give_back_marked(marked: np.ndarray, cur: np.ndarray, taken: np.ndarray, refused: np.ndarray,
                      streak: np.ndarray) -> None:  # pragma: no cover
    """``ModelLabeller._give_back`` of the markers ``marked`` (``ModelLabeller._marked``)."""
    for p in range(len(taken)):
        if marked[taken[p]]:  # -1 indexes the last entry, False
            refused[taken[p], p] = True
            taken[p] = -1
    for m in range(len(cur)):
        if marked[m]:
            cur[m] = np.nan
            streak[m] = 0


@njit(cache=True)
def _fit_segment(s: int, level: int, cur: np.ndarray, rot: np.ndarray, shift: np.ndarray, posed: np.ndarray,
                 levels: np.ndarray, before_rot: np.ndarray, before_shift: np.ndarray, before: np.ndarray,
                 posture: np.ndarray, posture_known: np.ndarray, first: np.ndarray, count: np.ndarray,
                 local: np.ndarray, weight: np.ndarray, joint_first: np.ndarray, joint_other: np.ndarray,
                 joint_here: np.ndarray, joint_there: np.ndarray, joint_tol: np.ndarray, joint_w: np.ndarray,
                 lay: np.ndarray, x: np.ndarray, w: np.ndarray, tols: np.ndarray, r: np.ndarray,
                 t: np.ndarray) -> float:  # pragma: no cover
    """Segment ``s``'s pose into ``r`` and ``t`` from its matched markers alone (``level`` 0: three or more), with the
    centres of its joints to surely posed segments (1: three points or more; 2: two, with its previous pose, carried
    by a surely posed neighbour where it has a posture to it); and how far the fit puts the farthest joint centre from
    where its neighbour does, in units of that joint's tolerance (0 with no joint centre). NaN for no pose."""
    seen = 0
    for m in range(first[s], first[s] + count[s]):
        if np.isfinite(cur[m, 0]):
            lay[seen], x[seen], w[seen] = local[m], cur[m], weight[m]
            seen += 1
    if seen == 0 or (seen < 3 and level == 0):
        return np.nan
    k, joints = seen, 0
    if seen < 3:
        for j in range(joint_first[s], joint_first[s + 1]):
            o = joint_other[j]
            if posed[o] and levels[o] < 2:
                lay[k], w[k], tols[joints] = joint_here[j], joint_w[j], joint_tol[j]
                place(rot[o], joint_there[j], shift[o], x[k])
                k += 1
                joints += 1
        if k < 2 or (k < 3 and (level < 2 or not before[s])):
            return np.nan
        if before[s]:
            prior_rot, prior_shift = before_rot[s], before_shift[s]
            for j in range(joint_first[s], joint_first[s + 1]):
                o = joint_other[j]
                if posed[o] and levels[o] < 2 and posture_known[s, o]:
                    prior_rot = rot[o] @ posture[s, o]
                    centre, turned = np.empty(3), np.empty(3)
                    place(rot[o], joint_there[j], shift[o], centre)
                    place(prior_rot, joint_here[j], np.zeros(3), turned)
                    prior_shift = centre - turned
                    break
            for m in range(first[s], first[s] + count[s]):
                lay[k], w[k] = local[m], PRIOR_WEIGHT
                place(prior_rot, local[m], prior_shift, x[k])
                k += 1
    if not kabsch_into(lay[:k], x[:k], w[:k] / w[:k].sum(), r, t):
        return np.nan
    excess = 0.0
    at = np.empty(3)
    for n in range(joints):
        place(r, lay[seen + n], t, at)
        excess = max(excess, distance(at, x[seen + n]) / tols[n])
    return excess


@njit(cache=True)
def _pose_by_markers(cur: np.ndarray, taken: np.ndarray, refused: np.ndarray, streak: np.ndarray, rot: np.ndarray,
                     shift: np.ndarray, posed: np.ndarray, levels: np.ndarray, before_rot: np.ndarray,
                     before_shift: np.ndarray, before: np.ndarray, posture: np.ndarray, posture_known: np.ndarray,
                     first: np.ndarray, count: np.ndarray, local: np.ndarray, tol: np.ndarray, weight: np.ndarray,
                     joint_first: np.ndarray, joint_other: np.ndarray, joint_here: np.ndarray,
                     joint_there: np.ndarray, joint_tol: np.ndarray, joint_w: np.ndarray) -> bool:  # pragma: no cover
    """``ModelLabeller._pose_segments``, compiled: each segment not posed (``posed``, ``rot``, ``shift``,
    ``levels``, changed in place) fitted by ``_fit_segment``, level after level, surest first. A fit that puts a joint
    centre beyond its tolerance gives all the segment's points back, one that puts a marker beyond its tolerance the
    worst one's, and the segment is fitted again (``cur``, ``taken``, ``refused``, ``streak`` changed in place). True
    when a segment was posed."""
    segments = len(first)
    width = 0
    for s in range(segments):
        width = max(width, 2 * count[s] + joint_first[s + 1] - joint_first[s])
    lay, x, w, tols = np.empty((width, 3)), np.empty((width, 3)), np.empty(width), np.empty(width)
    r, t, at = np.empty((3, 3)), np.empty(3), np.empty(3)
    matched = np.zeros(segments, np.int64)
    marked = np.zeros(len(cur) + 1, np.bool_)  # the markers to give back, as ``ModelLabeller._marked``
    any_posed = False
    for level in range(3):
        progress = True
        while progress:
            progress = False
            for s in range(segments):  # only a segment's own fit changes its count
                matched[s] = 0
                for m in range(first[s], first[s] + count[s]):
                    if np.isfinite(cur[m, 0]):
                        matched[s] += 1
            for s in range(segments):
                if posed[s] or matched[s] < (3 if level == 0 else 1):
                    continue
                excess = _fit_segment(s, level, cur, rot, shift, posed, levels, before_rot, before_shift, before,
                                      posture, posture_known, first, count, local, weight, joint_first, joint_other,
                                      joint_here, joint_there, joint_tol, joint_w, lay, x, w, tols, r, t)
                if np.isnan(excess):
                    continue
                if excess > 1.0:  # markers swapped, or taken by ghosts: the search decides
                    marked[first[s]:first[s] + count[s]] = True
                    _give_back_marked(marked, cur, taken, refused, streak)
                    marked[:] = False
                    continue
                worst, far, beyond = -1.0, -1, False
                for m in range(first[s], first[s] + count[s]):
                    ratio = 0.0
                    if np.isfinite(cur[m, 0]):
                        place(r, local[m], t, at)
                        error = distance(at, cur[m])
                        beyond = beyond or error > tol[m]
                        ratio = error / tol[m]
                    if ratio > worst:
                        worst, far = ratio, m
                if beyond:  # the worst one goes; the others decide again
                    marked[far] = True
                    _give_back_marked(marked, cur, taken, refused, streak)
                    marked[far] = False
                    progress = True
                    continue
                rot[s], shift[s], posed[s], levels[s] = r, t, True, level
                any_posed = progress = True
    return any_posed


@njit(cache=True)
def _predict(markers: np.ndarray, rot: np.ndarray, shift: np.ndarray, posed: np.ndarray, segment_of: np.ndarray,
             local: np.ndarray, tol: np.ndarray, fit_mm: float, pred: np.ndarray,
             gate: np.ndarray) -> None:  # pragma: no cover
    """``ModelLabeller._predicted`` into ``pred`` and ``gate`` (NaN and ``gate_mm`` given)."""
    for i in range(len(markers)):
        m = markers[i]
        s = segment_of[m]
        if posed[s]:
            place(rot[s], local[m], shift[s], pred[i])
            gate[i] += tol[m] - fit_mm


@njit(cache=True)
def _predicted_costs(cur: np.ndarray, taken: np.ndarray, z: np.ndarray, refused: np.ndarray, time: float,
                     rot: np.ndarray, shift: np.ndarray, posed: np.ndarray, levels: np.ndarray,
                     segment_of: np.ndarray, first: np.ndarray, count: np.ndarray, local: np.ndarray, tol: np.ndarray,
                     joint_first: np.ndarray, joint_other: np.ndarray, joint_here: np.ndarray,
                     joint_there: np.ndarray, joint_tol: np.ndarray, pos: np.ndarray, vel: np.ndarray,
                     last: np.ndarray, gate_mm: float, fit_mm: float, weak_gate_mm: float,
                     max_coast_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """For ``ModelLabeller._take_predicted``: the unmatched markers with a prediction (their segment's pose, else a
    coast at constant velocity for ``max_coast_s``), the points of ``z`` left over, and the cost of giving each such
    point to each such marker (``gated_cost``; 0 where not allowed: ``_weakly_posed``'s checks, or a point the
    marker's fit gave back this frame, ``refused``)."""
    missing = np.flatnonzero(np.isnan(cur[:, 0]))
    free = np.flatnonzero(taken < 0)
    if not len(missing) or not len(free):
        return missing[:0], free[:0], np.zeros((0, 0))
    pred, gate = np.full((len(missing), 3), np.nan), np.full(len(missing), gate_mm)
    _predict(missing, rot, shift, posed, segment_of, local, tol, fit_mm, pred, gate)
    allowed = np.ones((len(missing), len(free)), np.bool_)
    points = z[free]
    _weakly_posed(missing, points, cur, rot, shift, posed, levels, segment_of, first, count, local, tol, joint_first,
                  joint_other, joint_here, joint_there, joint_tol, weak_gate_mm, pred, gate, allowed)
    known = np.empty(len(missing), np.intp)
    n = 0
    for i in range(len(missing)):
        m = missing[i]
        dt = time - last[m]
        if np.isnan(pred[i, 0]) and dt <= max_coast_s:
            for a in range(3):
                pred[i, a] = pos[m, a] + vel[m, a] * dt
        if np.isfinite(pred[i, 0]):
            known[n] = i
            n += 1
    known = known[:n]
    hypotheses, gates = np.empty((n, 1, 3)), np.empty((n, 1))
    for k in range(n):
        hypotheses[k, 0], gates[k, 0] = pred[known[k]], gate[known[k]]
    cost = gated_cost_compiled(hypotheses, gates, points)
    for k in range(n):
        for p in range(len(free)):
            if not allowed[known[k], p] or refused[missing[known[k]], free[p]]:
                cost[k, p] = 0.0
    return missing[known], free, cost


@njit(cache=True)
def _weakly_posed(missing: np.ndarray, points: np.ndarray, cur: np.ndarray, rot: np.ndarray, shift: np.ndarray,
                  posed: np.ndarray, levels: np.ndarray, segment_of: np.ndarray, first: np.ndarray, count: np.ndarray,
                  local: np.ndarray, tol: np.ndarray, joint_first: np.ndarray, joint_other: np.ndarray,
                  joint_here: np.ndarray, joint_there: np.ndarray, joint_tol: np.ndarray, weak_gate_mm: float,
                  pred: np.ndarray, gate: np.ndarray, allowed: np.ndarray) -> None:  # pragma: no cover
    """For ``ModelLabeller._take_predicted``: the ``missing`` markers of segments posed through joints or with a turn
    left to their previous pose (``levels`` 1 or 2) get ``weak_gate_mm`` (``gate``); where such a marker's prediction
    (``pred``) has one of the free ``points`` within that gate, it may take (``allowed`` (missing, points)) only a
    point keeping the layout's distances to its segment's markers seen now and to the centres of its joints to surely
    posed neighbours, each within the larger of the two's tolerances, and only where neither the point nor the
    marker has another such candidate."""
    width = 0
    for s in range(len(first)):
        width = max(width, count[s] + joint_first[s + 1] - joint_first[s])
    here, there, limit = np.empty((width, 3)), np.empty((width, 3)), np.empty(width)
    slots = np.empty(len(missing), np.intp)
    fits = np.zeros((len(missing), len(points)), np.bool_)
    for s in range(len(first)):
        if not posed[s] or levels[s] == 0:
            continue
        n, near = 0, False
        for i in range(len(missing)):
            if segment_of[missing[i]] == s:
                slots[n] = i
                n += 1
                gate[i] = weak_gate_mm
                for p in range(len(points)):
                    near = near or distance(pred[i], points[p]) < weak_gate_mm
        if not near:
            continue  # no point to take: what could be is not worked out
        k = 0
        for m in range(first[s], first[s] + count[s]):
            if np.isfinite(cur[m, 0]):
                here[k], there[k], limit[k] = local[m], cur[m], tol[m]
                k += 1
        for j in range(joint_first[s], joint_first[s + 1]):
            o = joint_other[j]
            if posed[o] and levels[o] < 2:
                here[k], limit[k] = joint_here[j], joint_tol[j]
                place(rot[o], joint_there[j], shift[o], there[k])
                k += 1
        for a in range(n):
            m = missing[slots[a]]
            for p in range(len(points)):
                fit = True
                for r in range(k):
                    fit = fit and abs(distance(points[p], there[r]) - distance(local[m], here[r])) < max(tol[m],
                                                                                                       limit[r])
                fits[a, p] = fit
        for a in range(n):
            for p in range(len(points)):
                alone = fits[a, p]
                for b in range(n):
                    alone = alone and (b == a or not fits[b, p])
                for q in range(len(points)):
                    alone = alone and (q == p or not fits[a, q])
                allowed[slots[a], p] = alone


@njit(cache=True)
def _remember_postures(rot: np.ndarray, sure: np.ndarray, joint_first: np.ndarray, joint_other: np.ndarray,
                       posture: np.ndarray, known: np.ndarray) -> None:  # pragma: no cover
    """Each segment's rotation relative to each neighbour (``posture``, ``known``) where both are ``sure``ly posed."""
    for s in range(len(sure)):
        for j in range(joint_first[s], joint_first[s + 1]):
            o = joint_other[j]
            if sure[s] and sure[o]:
                for a in range(3):
                    for b in range(3):
                        posture[s, o, a, b] = rot[o, 0, a] * rot[s, 0, b] + rot[o, 1, a] * rot[s, 1, b] \
                            + rot[o, 2, a] * rot[s, 2, b]
                known[s, o] = True
