"""The streaming occlusion filler: a Kalman filter per marker fed by the rigid-body constraint cases (Aristidou 2008,
ch. 5; the package's docstring lists the cases and the changes to the thesis)."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from numba import njit
from scipy.spatial.transform import Rotation

from mocapflow.mocap.filling.body import Body, joint_centres
from mocapflow.mocap.filling.config import FillerConfig, FillResult
from mocapflow.mocap.filling.geometry import nearest_on_circle, project_on_rays, slide_on_rays, swing, unit
from mocapflow.mocap.filling.learner import SkeletonLearner, is_complete
from mocapflow.mocap.filling.memory import MotionMemory
from mocapflow.mocap.flags import (
    CASE_KALMAN,
    CASE_MISSING,
    CASE_OBSERVED,
    CASE_ONE_MISSING,
    CASE_TWO_MISSING,
    FillCase,
)
from mocapflow.mocap.kalman import ConstantVelocityBank
from mocapflow.mocap.markerset import added
from mocapflow.mocap.model import SkeletonModel
from mocapflow.mocap.rigidfit import finite, fit_one, kabsch_into, place


class Hold(NamedTuple):
    """The rotation of a segment placed through two anchors, held since its gap began: the anchors it was taken
    for (``key``: reference segment and the two anchor names), the anchor line's direction and the rotation, both in
    the reference's frame."""

    key: tuple[int, tuple[str, int], tuple[str, int]]
    axis: np.ndarray
    rotation: np.ndarray


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
                                   cfg.rotor_sd, cfg.ray_sd, cfg.kinematic_sd]) ** 2  # per FillCase (unused where
        # nothing is measured)
        self._unmeasured = np.zeros(n, dtype=np.int64)  # frames since a marker was last seen or anchored
        self._coasting = np.ones(n)  # where ``_next_gain`` writes the velocity factors
        self._gain: np.ndarray | None = None  # of the next prediction (``_next_gain``); None: 1 for every marker
        self._extrapolated = np.zeros(n, dtype=bool)  # this frame: predicted from its past alone (a constant rotor
        # with no anchor, or its filter along its ray)
        self._last = np.full((2, n, 3), np.nan)  # the last two filled frames, newest first
        self.body: Body | None = None
        self._model: SkeletonModel | None = None
        self._pose_r = np.zeros((2, 0, 3, 3))
        self._pose_t = np.zeros((2, 0, 3))
        self._pose_ok = np.zeros((2, 0), dtype=bool)
        self._pose_fresh = np.zeros((2, 0), dtype=bool)  # per segment: pose this frame / last frame known
        self._learner: SkeletonLearner | None = None
        self._pending: SkeletonModel | None = None  # learned, taken up at the next frame
        self._holds: dict[int, Hold] = {}
        self._held: set[int] = set()  # segments whose hold was used this frame
        self._given: SkeletonModel | None = None  # the model given from outside, if any
        self._memory: MotionMemory | None = None  # of the body in use
        self._kinematic_weight = cfg.joint_weight * (cfg.joint_sd / cfg.kinematic_sd) ** 2  # a learnt marker's
        # weight in a fit, next to a joint's
        if skeleton is not None:
            self.set_skeleton(skeleton)
        elif cfg.learn:
            self._learner = SkeletonLearner(self.labels, self.rate, cfg, None)

    # -- model -------------------------------------------------------------------------------------------------
    def set_skeleton(self, skeleton: SkeletonModel) -> None:
        """Adopt a new body model mid-stream. What it leaves open (segments without marker offsets, joints without
        offsets) is learned from then on when ``config.learn``; poses restart from the last two filled frames."""
        complete = is_complete(skeleton)
        self._given = skeleton
        self._learner = None if complete or not self.config.learn else SkeletonLearner(
            self.labels, self.rate, self.config, skeleton)
        self._pending = None
        self._adopt(skeleton)

    def grow(self, labels: list[str]) -> None:
        """Take on the markers appended to the label order (``markerset``: the marker set only grows), keeping every
        marker's filter and the body model in use. Learning starts again over the larger set (the model learned so
        far stays in use until it gives a new one); a given model keeps its segments and joints."""
        new = added(self.labels, labels)
        if new is None:
            raise ValueError("the labels do not extend the filler's: a new marker set needs a new filler")
        if not new:
            return
        extra = len(new)
        self.labels = list(labels)
        self.kf.grow(extra)
        self._unmeasured = np.append(self._unmeasured, np.zeros(extra, dtype=np.int64))
        self._coasting = np.ones(len(self.labels))
        self._next_gain()
        self._extrapolated = np.append(self._extrapolated, np.zeros(extra, dtype=bool))
        self._last = np.concatenate([self._last, np.full((2, extra, 3), np.nan)], axis=1)
        if self._learner is not None:
            self._learner = SkeletonLearner(self.labels, self.rate, self.config, self._given)
            self._pending = None
        if self._model is not None:
            self._adopt(self._model)

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
        self.body = Body(skeleton, self.labels)
        s = len(self.body.members)
        self._memory = MotionMemory(self.body, self.rate, self.config, self._memory)
        self._pose_r = np.zeros((2, s, 3, 3))
        self._pose_t = np.zeros((2, s, 3))
        self._pose_ok = np.zeros((2, s), dtype=bool)
        self._pose_fresh = np.zeros((2, s), dtype=bool)  # fitted from the last two filled frames when next needed

    @staticmethod
    def _fitted_poses_for(body: Body, filled: np.ndarray, segments: np.ndarray
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
        return self.kf.predicted_position(self._gain)

    def _next_gain(self) -> None:
        """The per-marker velocity factor of the next prediction, set anew whenever ``_unmeasured`` changes: markers
        without news coast to rest."""
        self._gain = self._coasting if _coast_gains(self._unmeasured, self._coast_gain, self._coasting) else None

    def update(self, positions: np.ndarray, rays: np.ndarray | None = None) -> FillResult:
        """Fill one frame. ``positions`` (N, 3) in label order, NaN where missing; ``rays`` (N, 6) optional origin
        and direction of the single camera ray of a marker seen by one camera (NaN rows otherwise)."""
        n = len(self.labels)
        z = np.array(positions, dtype=float).reshape(n, 3)
        if self._pending is not None:
            self._adopt(self._pending)
            self._pending = None
        self.kf.predict(self._gain)
        # a marker seen in the previous frame and now ``outlier_mm`` or more from its prediction is an outlier: no
        # marker moves so in one frame, so it would only pull the filter and the segment fits off
        seen, flags = np.empty(n, dtype=bool), np.empty(n, dtype=np.uint8)
        every = _screened(z, self.kf.position, self.config.outlier_mm, self._unmeasured, self._extrapolated, seen,
                          flags)
        body = self.body
        poses = None
        if not every:  # else every marker observed: each is its own measurement and its own output
            poses = self._fill_missing(z, seen, flags, rays)
        variance, measured = np.empty(n), np.empty(n, dtype=bool)
        _measurements(flags, self._variance, variance, measured)
        self.kf.update(z, variance, measured)
        _filtered_out(z, flags, self.kf.position, measured, self._extrapolated, self._unmeasured)
        self._next_gain()

        self._last[1] = self._last[0]
        self._last[0] = z
        centres: np.ndarray | Callable[[], np.ndarray] | None = None
        memory = self._memory
        if body is not None and memory is not None:
            self._pose_r[1], self._pose_t[1], self._pose_ok[1] = self._pose_r[0], self._pose_t[0], self._pose_ok[0]
            self._pose_fresh[1] = self._pose_fresh[0]
            if poses is None:  # no segment lost a marker: the fit waits until a gap or a reader needs it
                self._pose_fresh[0] = False
                self._holds.clear()  # a later gap starts its own holds and models
                memory.kinematic.forget()
            else:  # the constraint's own poses around the gaps, so estimates cannot creep through the filter's lag
                self._pose_r[0], self._pose_t[0], self._pose_ok[0], self._pose_fresh[0] = poses
            centres = self._centres_later(z, flags, poses)
            memory.observe(z, seen)
        if self._learner is not None:  # a new model is taken up from the next frame, so the result and
            # ``joint_names`` keep describing the same body until then
            self._pending = self._learner.observe(z, seen, flags, body, self._current_poses) or self._pending
        return FillResult(positions=z, flags=flags, joint_centres=centres)

    def _current_poses(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """This frame's segment poses, fitted now where skipped."""
        self._ensure_poses(ages=1)
        return self._pose_r[0].copy(), self._pose_t[0].copy(), self._pose_ok[0].copy()

    def _centres_later(self, z: np.ndarray, flags: np.ndarray,
                       poses: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None) -> Callable[[], np.ndarray]:
        """The joint centres of this frame, computed on first read from its ``poses`` (R, t, known, fitted: those
        ``_constrain`` worked out, none without a gap), the others fitted then."""
        body = self.body
        assert body is not None
        flags, z = flags.copy(), z.copy()  # the caller may edit the result's arrays before reading the centres

        def centres() -> np.ndarray:
            if poses is None:
                return joint_centres(body, self._fitted_poses_for(body, z, np.arange(len(body.members))), flags)
            r, t, ok, fresh = poses
            stale = np.flatnonzero(~fresh)
            if len(stale):
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
        missing = ~seen
        body = self.body if self.body is not None and (missing & self.body.in_segment).any() else None
        near = np.zeros(0, dtype=int)
        if body is not None:
            near = body.around(missing)
        visible = seen.copy()
        fit_all = False  # pose every segment near the gaps, not only those holding one (see ``_constrain``)
        if rays is not None:
            rays = np.asarray(rays, dtype=float).reshape(n, 6)
            ray_rows = ~seen & np.isfinite(rays).all(axis=1) & (np.linalg.norm(rays[:, 3:], axis=1) > 0)
            if ray_rows.any():
                fit_all = True
                guess = prior.copy()
                anchored = np.zeros(n, dtype=bool)
                if body is not None:
                    est, _, _ = self._constrain(z, visible, prior, ray_rows & body.in_segment, near, False, fit_all)
                    anchored = np.isfinite(est).all(axis=1)
                    guess[anchored] = est[anchored]
                ok = ray_rows & np.isfinite(guess).all(axis=1)
                self._extrapolated |= ok & ~anchored  # nothing holds it along its ray: there it coasts to rest
                z[ok] = project_on_rays(guess[ok], rays[ok])
                if body is not None and self.config.ray_distances:
                    slide_on_rays(z, seen, rays, np.flatnonzero(ok & body.in_segment), body.marker_seg,
                                  body.members, body.offsets, (self.config.observed_sd / self.config.ray_sd) ** 2)
                flags[ok] = FillCase.RAY
                visible |= ok
        poses = None
        targets = np.zeros(n, dtype=bool)
        est, codes = prior, flags  # no rigid-body estimate
        if body is not None:
            targets = ~visible & body.in_segment
            self._held = set()
            memory = self._memory
            assert memory is not None
            memory.kinematic.start_frame()
            est, codes, poses = self._constrain(z, visible, prior, targets, near, True, fit_all)
            if self._holds:
                self._holds = {k: hold for k, hold in self._holds.items() if k in self._held}
            memory.kinematic.end_frame()
        _take_estimates(z, flags, est, codes, targets, prior, self._extrapolated, self._unmeasured,
                        np.iinfo(np.int64).max if self._max_coast is None else self._max_coast)
        return poses

    def _constrain(
        self, filled: np.ndarray, visible: np.ndarray, prior: np.ndarray, targets: np.ndarray, near: np.ndarray,
        keep: bool, fit_all: bool,
    ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """Rigid-body estimates (5.3) of the ``targets`` markers from the ``visible`` ones: (N, 3), case codes, and
        the poses this frame (R, t, known, and which segments these were worked out for) of the segments holding a
        target and, when one of them must be placed through its neighbours or with ``fit_all``, of the other
        segments ``near`` them (the others are left unknown): fitted to their visible markers when three or more
        are, else as placed here. A neighbour left out has all its markers visible, so its pose is fitted from the
        filled frame later, alike, if a gap or a reader needs it; ``fit_all`` (single-camera markers, whose filled
        positions are not their measurements) poses them all now. ``keep`` stores the two-anchor holds (off for the
        single-camera pass)."""
        body = self.body
        memory = self._memory
        assert body is not None and memory is not None
        cfg = self.config
        n = len(self.labels)
        est = np.empty((n, 3))
        est.fill(np.nan)  # half the cost of np.full
        codes = np.zeros(n, dtype=np.uint8)
        layout = body.layout(visible, targets, near)
        seg_vis = layout.seg_vis
        s = len(body.members)
        r_all, t_all = np.zeros((s, 3, 3)), np.zeros((s, 3))
        posed, fresh = np.zeros(s, dtype=bool), np.zeros(s, dtype=bool)
        first, later = layout.first, layout.later
        layout.fit_first.into(filled, r_all, t_all, posed)  # three visible markers fix a pose
        fresh[first] = True
        _place_on_poses(r_all, t_all, posed, layout.target_rows, layout.target_seg, layout.target_local, est, codes)
        waiting = np.zeros(s, dtype=bool)  # segments holding a target not yet placed
        waiting[layout.segments] = ~posed[layout.segments]
        if (fit_all or waiting.any()) and len(later):
            layout.fit_later.into(filled, r_all, t_all, posed)
            fresh[later] = True
        seen_posed = posed.copy()  # placed with at least one of their own markers visible
        # the waiting segments are placed through their neighbours' joints, in passes from the most visible down, so
        # that one placed can anchor the next (a pass that places none sets ``force``: the rest keep their last
        # rotation rate); the compiled pass places those with a visible marker and three or more anchors, and hands
        # each of the others here
        state = np.zeros(3, dtype=np.int64)  # the pass's cursor, whether it placed one, ``force``
        last_known = False  # the last frames' poses, fitted where skipped, which only the segments handed here need
        while (k := _place_through_joints(
                filled, layout.by_vis, state, waiting, seg_vis, body.idx, body.local, layout.vis_slot,
                layout.hit_slot, body.link_count, body.link_other, body.link_own, body.link_theirs, cfg.joint_weight,
                cfg.joint_anchors == "partial", r_all, t_all, posed, seen_posed, est, codes)) >= 0:
            if not last_known:
                self._ensure_poses(near)
                last_known = True
            waiting[k] = False
            state[1] = True
            seen_rows, _, _, miss, hit = layout.parts[k]
            nv = int(seg_vis[k])
            links = [link for link in body.links[k] if posed[link[1]]]
            reference = None  # a posed neighbour, preferring one placed with its own markers seen, then the
            best = (True, np.inf)  # one whose twist relative to this segment has varied least
            for j, other, _, _ in links:
                if not self._pose_ok[0, other]:
                    continue
                rank = (not seen_posed[other], memory.twist.spread(k, j))
                if reference is None or rank < best:
                    best, reference = rank, (other, r_all[other], self._pose_r[0, other])
            learnt = None if nv or not cfg.kinematic_model else memory.kinematic.points(
                k, [other for _, other, _, _ in links if seen_posed[other]], reference and reference[0],
                body.offsets[k], r_all, t_all)
            if not (nv == 0 or cfg.joint_anchors == "partial"):
                links = []
            a, w, anchors = layout.anchors(k, links, cfg.joint_weight)
            p = np.empty((nv + len(links), 3))
            p[:nv] = filled[seen_rows]
            for i, (_, other, _, theirs) in enumerate(links, start=nv):
                p[i] = r_all[other] @ theirs + t_all[other]
            if learnt is not None:  # the learnt markers join the joints: they fix the twist the joints leave
                p, a = np.concatenate([p, learnt]), np.concatenate([a, body.offsets[k]])
                w = np.concatenate([w, np.full(len(learnt), self._kinematic_weight)])
            via_seen = any(seen_posed[other] for _, other, _, _ in links)
            placed = self._estimate_segment(k, p, a, w, anchors, reference, prior, keep)
            if placed is None:
                continue
            r, t, points_on_circle = placed
            est[miss] = (points_on_circle if points_on_circle is not None else body.offsets[k] @ r.T + t)[hit]
            if learnt is not None:
                codes[miss] = FillCase.LEARNT
            elif seg_vis[k] >= 2:
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
        return est, codes, (r_all, t_all, posed, fresh)

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
            fit = fit_one(a, p, w)
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
            if hold is None or hold.key != key:
                hold = Hold(key, relative @ unit(a[1] - a[0]), relative)
            if keep:
                self._holds[k] = hold
                self._held.add(k)
            r = frame @ swing(hold.axis, frame.T @ unit(p[1] - p[0])) @ hold.rotation
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


@njit(cache=True)
def _place_on_poses(r: np.ndarray, t: np.ndarray, posed: np.ndarray, rows: np.ndarray, seg: np.ndarray,
                    local: np.ndarray, est: np.ndarray, codes: np.ndarray) -> None:  # pragma: no cover
    """Each target (``rows``, at ``local`` in segment ``seg``) of a ``posed`` segment placed by its pose (R, t), in
    place: ``est`` and ``codes`` (``CASE_ONE_MISSING``)."""
    for i in range(len(rows)):
        k = seg[i]
        if posed[k]:
            place(r[k], local[i], t[k], est[rows[i]])
            codes[rows[i]] = CASE_ONE_MISSING


@njit(cache=True)
def _place_through_joints(filled: np.ndarray, order: np.ndarray, state: np.ndarray, waiting: np.ndarray,
                          seg_vis: np.ndarray, idx: np.ndarray, local: np.ndarray, vis_slot: np.ndarray,
                          hit_slot: np.ndarray, link_count: np.ndarray, link_other: np.ndarray, link_own: np.ndarray,
                          link_theirs: np.ndarray, joint_weight: float, partial: bool, r_all: np.ndarray,
                          t_all: np.ndarray, posed: np.ndarray, seen_posed: np.ndarray, est: np.ndarray,
                          codes: np.ndarray) -> int:  # pragma: no cover
    """The passes of ``GapFiller._constrain`` over the ``waiting`` segments (in ``order``), in place, from where
    ``state`` (cursor, placed one this pass, ``force``) left them. A segment with a visible marker and three or more
    anchors (its visible markers, then the centres of its joints with posed neighbours, when ``partial`` or it has
    no visible marker) that fix a rotation is fitted to them here: its pose, its targets' estimates and codes. The
    first other segment to place is returned for the caller to place (-1: none left); skipped until ``force``
    while it has no anchor."""
    cursor, progress, force = state[0], state[1] != 0, state[2] != 0
    width = idx.shape[1] + link_other.shape[1]
    p, a, w = np.empty((width, 3)), np.empty((width, 3)), np.empty(width)
    r, t = np.empty((3, 3)), np.empty(3)
    while waiting.any():
        while cursor < len(order):
            k = order[cursor]
            cursor += 1
            if not waiting[k]:
                continue
            nv = seg_vis[k]
            joints = nv == 0 or partial
            m = nv
            for i in range(link_count[k] if joints else 0):
                m += posed[link_other[k, i]]
            if m == 0 and not force:
                continue
            c = 0
            if nv and m >= 3:
                for slot in range(idx.shape[1]):
                    if vis_slot[k, slot]:
                        p[c], a[c], w[c] = filled[idx[k, slot]], local[k, slot], 1.0
                        c += 1
                for i in range(link_count[k] if joints else 0):
                    other = link_other[k, i]
                    if posed[other]:
                        place(r_all[other], link_theirs[k, i], t_all[other], p[c])
                        a[c], w[c] = link_own[k, i], joint_weight
                        c += 1
            if c == 0 or not kabsch_into(a[:c], p[:c], w[:c] / w[:c].sum(), r, t):
                state[0], state[1], state[2] = cursor, progress, force
                return k
            for slot in range(idx.shape[1]):
                if hit_slot[k, slot]:
                    place(r, local[k, slot], t, est[idx[k, slot]])
                    codes[idx[k, slot]] = CASE_ONE_MISSING if nv >= 2 else CASE_TWO_MISSING
            r_all[k], t_all[k] = r, t
            posed[k] = seen_posed[k] = True
            waiting[k] = False
            progress = True
        cursor, force, progress = 0, not progress, False
    return -1


@njit(cache=True)
def _screened(z: np.ndarray, predicted: np.ndarray, limit: float, unmeasured: np.ndarray, extrapolated: np.ndarray,
              seen: np.ndarray, flags: np.ndarray) -> bool:  # pragma: no cover
    """The start of ``GapFiller.update``, in place, marker by marker: a row of ``z`` is ``seen`` (and flagged
    ``CASE_OBSERVED``, else ``CASE_MISSING`` and NaN) when it holds a position that, for a marker measured last frame
    (``unmeasured`` 0), lies less than ``limit`` from its filter's ``predicted`` one (a filter not started yet
    rejects nothing); ``extrapolated`` cleared. Whether every row is seen."""
    every = True
    for i in range(len(z)):
        ok = finite(z[i])
        if ok and unmeasured[i] == 0:
            d0, d1, d2 = z[i, 0] - predicted[i, 0], z[i, 1] - predicted[i, 1], z[i, 2] - predicted[i, 2]
            ok = not np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) >= limit  # NaN (filter not started): kept
        if not ok:
            z[i, :] = np.nan
        seen[i] = ok
        flags[i] = CASE_OBSERVED if ok else CASE_MISSING
        extrapolated[i] = False
        every &= ok
    return every


@njit(cache=True)
def _measurements(flags: np.ndarray, noise: np.ndarray, variance: np.ndarray,
                  measured: np.ndarray) -> None:  # pragma: no cover
    """What the filters take from a filled frame, marker by marker: ``measured`` (observed or estimated, not a filter
    coasting alone) with the ``variance`` of its case (``noise``, per ``FillCase``)."""
    for i in range(len(flags)):
        measured[i] = flags[i] >= CASE_OBSERVED and flags[i] != CASE_KALMAN
        variance[i] = noise[flags[i]]


@njit(cache=True)
def _take_estimates(z: np.ndarray, flags: np.ndarray, est: np.ndarray, codes: np.ndarray, targets: np.ndarray,
                    prior: np.ndarray, extrapolated: np.ndarray, unmeasured: np.ndarray,
                    max_coast: int) -> None:  # pragma: no cover
    """The end of ``GapFiller._fill_missing``, in place, marker by marker: a ``targets`` marker with a rigid-body
    estimate (``est``, case ``codes``) takes it, one with no other news than its filter's ``prior`` takes that
    (``CASE_KALMAN``); a marker extrapolated from its past alone only until ``max_coast`` frames without news."""
    for i in range(len(z)):
        fresh = unmeasured[i] < max_coast
        if targets[i] and finite(est[i]) and (fresh or not extrapolated[i]):
            z[i, :] = est[i]
            flags[i] = codes[i]
        if flags[i] == CASE_MISSING and fresh and finite(prior[i]):
            z[i, :] = prior[i]
            flags[i] = CASE_KALMAN


@njit(cache=True)
def _filtered_out(z: np.ndarray, flags: np.ndarray, position: np.ndarray, measured: np.ndarray,
                  extrapolated: np.ndarray, unmeasured: np.ndarray) -> None:  # pragma: no cover
    """After the filters' update, in place, marker by marker: an estimated marker's output is its filter's
    ``position``; ``unmeasured`` counts the frames since a marker was last ``measured`` (not ``extrapolated``)."""
    for i in range(len(z)):
        if flags[i] >= CASE_ONE_MISSING:
            z[i, :] = position[i]
        unmeasured[i] = 0 if measured[i] and not extrapolated[i] else unmeasured[i] + 1


@njit(cache=True)
def _coast_gains(unmeasured: np.ndarray, coast: float, gain: np.ndarray) -> bool:  # pragma: no cover
    """``GapFiller._next_gain`` into ``gain``, marker by marker: ``coast`` for a marker ``unmeasured`` since one
    frame or more, 1 for the others. Whether any is."""
    coasting = False
    for i in range(len(unmeasured)):
        gain[i] = coast if unmeasured[i] > 0 else 1.0
        coasting |= unmeasured[i] > 0
    return coasting
