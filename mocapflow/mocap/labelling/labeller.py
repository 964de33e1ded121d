"""The streaming labeller: one persistent identity per physical marker, frame by frame (the package's docstring
describes the method)."""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy.spatial.distance import cdist

from mocapflow.mocap.labelling.assignment import (
    distance,
    gated_cost,
    gated_cost_compiled,
    match,
    norm,
    screened,
    unambiguous,
)
from mocapflow.mocap.labelling.config import UNGATED_MM, LabellerConfig, LabelResult
from mocapflow.mocap.labelling.placement import place_marker
from mocapflow.mocap.labelling.tracks import Tentatives, Tracks
from mocapflow.mocap.rigidfit import finite


class Labeller:
    """Streaming labeller: feed frames in time order to :meth:`update`; ``labels`` grows as markers are confirmed."""

    def __init__(self, config: LabellerConfig, rate: float) -> None:
        if rate <= 0:
            raise ValueError("rate must be positive")
        self.config = config
        self.rate = float(rate)
        self.follow_mm = config.follow_gate(self.rate)  # the widest gate of a track seen in the last frame
        self.labels: list[str] = []
        self.frame = 0
        self._time = -np.inf
        self._tracks = Tracks(config, self.rate)
        # tentative tracks and the points they have collected, a second of them at most
        self._tentative = Tentatives(int(self.rate))

    @property
    def tracks(self) -> Tracks:
        """The confirmed tracks' state, for a caller that places lost tracks itself (``mocap.reacquire``)."""
        return self._tracks

    def set_segments(self, segments: list[list[int]]) -> None:
        """Declare groups of track indices that move rigidly: a track's segment mates become its neighbours.

        Tracks switch to their new neighbours when next seen, so a marker hidden now keeps the snapshots that can
        still find it.
        """
        n = len(self.labels)
        mates = np.zeros((n, n), bool)
        for seg in segments:
            idx = np.asarray(seg, np.intp)
            if np.any((idx < 0) | (idx >= n)):
                raise ValueError(f"segment {list(seg)} names a track outside 0..{n - 1}")
            mates[np.ix_(idx, idx)] = True
        np.fill_diagonal(mates, False)
        self._tracks.set_mates(mates)

    def update(self, points: np.ndarray, time: float, predictions: np.ndarray | None = None,
               rays: np.ndarray | None = None) -> LabelResult:
        """Label one frame of points ``(M, 3)`` (NaN rows ignored) captured at ``time`` seconds (increasing).

        ``predictions`` ``(T, 3)``, in track order with NaN where unknown, are positions of the current tracks
        predicted elsewhere (a gap filler); they replace the internal prediction when re-identifying lost tracks.
        ``rays`` ``(M, 6)``, by row of ``points`` with NaN where none, are single-camera rays (origin, direction) of
        markers the tracker could not place; each goes to the unseen track expected nearest its line (``_ray_owners``).
        """
        cfg = self.config
        if time <= self._time:
            raise ValueError(f"frame times must increase: {time} after {self._time}")
        self._time = time
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        rows = _finite_rows(np.ascontiguousarray(pts))
        z = np.ascontiguousarray(pts if len(rows) == len(pts) else pts[rows])  # one compiled form for every caller
        n_tracks = len(self.labels)
        if predictions is not None:
            predictions = np.asarray(predictions, dtype=float)
            if predictions.shape != (n_tracks, 3):
                raise ValueError(f"predictions must have shape ({n_tracks}, 3), got {predictions.shape}")
        tracks = self._tracks

        # 1. tracks seen in the previous frame: constant-velocity prediction, gated optimal assignment
        live, cost, unique, cur, taken, lost, free = _step_one(tracks.pos, tracks.vel, tracks.last, tracks.streak,
                                                               time, cfg.gate_mm, self.follow_mm, z, n_tracks)
        if not unique:  # a track or a point with two candidates: the optimal assignment
            ti, pi = match(cost)
            cur, taken, lost, free = _matched(live[ti], pi, z, n_tracks)

        # 2. the others: re-identification from rigid neighbours or outside predictions, else a short coast; with no
        # point left over (most frames) there is nothing to re-identify, and nothing to confirm in step 3 either
        if len(free) and len(lost):
            lost_pred, lost_gate, instant = self._lost_predictions(lost, cur, time, predictions, z[free])
            self._reidentify(lost, lost_pred, lost_gate, instant, cur, z, taken, free)
        else:  # no hypotheses needed
            lost_pred, lost_gate = np.empty((len(lost), 2, 3)), np.empty((len(lost), 2))
        tracks.observe(cur, time)

        # 3. tentative tracks on what is left; the long-lived ones become markers, the younger ones that surely are a
        # lost marker go back to it at once
        at = self._advance_tentatives(z, free[taken[free] < 0], time)
        history: list[tuple[int, np.ndarray, np.ndarray]] = []
        hits = self._tentative.hits
        # some point was left over, so any lost track has its hypotheses; with no lost track, only a tentative track
        # that has lived long enough can become a marker (in most frames with a ghost, none)
        if len(at) and (len(lost) or hits.max() >= cfg.confirm_frames):
            ready, young = np.flatnonzero(hits >= cfg.confirm_frames), np.flatnonzero(hits < cfg.confirm_frames)
            still = np.isnan(cur[lost, 0])
            owners = np.empty(0, np.intp)
            if len(ready):
                owners = self._owners(z[at[ready]], cur, lost[still], lost_pred[still], lost_gate[still])
                owned = np.zeros(len(self.labels), bool)
                owned[owners[owners >= 0]] = True
                still[still] = ~owned[lost[still]]
            sure = self._sure_owners(z[at[young]], hits[young], cur, lost[still])
            ready, owners = np.concatenate([ready, young]), np.concatenate([owners, sure])
            done = owners >= 0
            if done.any():  # most frames: a passing ghost, left tentative
                if len(self.labels) > n_tracks:  # new tracks confirmed
                    cur = np.vstack([cur, np.full((len(self.labels) - n_tracks, 3), np.nan)])
                history = self._adopt(ready, owners)
                cur[owners[done]] = z[at[ready[done]]]
                taken[at[ready[done]]] = owners[done]
        ray_out = None
        if rays is not None:
            rays = np.asarray(rays, dtype=float)
            if rays.shape != (len(pts), 6):
                raise ValueError(f"rays must have shape ({len(pts)}, 6), one per row of points, got {rays.shape}")
            ray_out = self._ray_owners(rays, cur, time, predictions)
        tracks.learn(cur, time, self.frame)
        self.frame += 1
        point_track = np.full(len(pts), -1, np.intp)
        point_track[rows] = taken
        return LabelResult(positions=cur, point_track=point_track, history=history, rays=ray_out)

    def _reidentify(self, lost: np.ndarray, pred: np.ndarray, gate: np.ndarray, instant: np.ndarray, cur: np.ndarray,
                    z: np.ndarray, taken: np.ndarray, free: np.ndarray) -> None:
        """Give the ``free`` points of ``z`` to the ``lost`` tracks whose hypotheses (``_lost_predictions``; the
        placement by neighbours only where ``instant``) they fit, screened by their rigid partners; in place in
        ``cur`` and ``taken``. The screening only ever raises a cost, so it is skipped when no point is in a gate."""
        points = z[free]
        has, cost = _instant_costs(pred, gate, instant, points)
        if not (cost < 0.0).any():
            return
        broken, partners, violated = self._tracks.signature(lost, cur, points)
        cost = screened(cost, broken[has], partners[has], violated[has])
        # A coast's gate grows with the time lost, and a segment mate of the marker, lost too, may come back inside
        # it first. A point is not taken on the coast alone (it stays tentative until the evidence tells them apart)
        # when another lost track's rigid partners seen now explain it as well, or when no rigid partner of the
        # track is seen and one lost with it lies within reach of the gate.
        rival = _rival_fit(broken, partners, has)
        ambiguous = (rival < np.inf) & ((partners[has] == 0) | (rival <= broken[has]))
        ambiguous |= (partners[has] == 0) & self._mate_within(lost[has], gate[has, 1], lost)[:, None]
        cost = np.where(ambiguous & _on_coast_only(pred[has], gate[has], points, instant[has]), 0.0, cost)
        ti, pi = match(cost)
        cur[lost[has[ti]]] = z[free[pi]]
        taken[free[pi]] = lost[has[ti]]

    def _mate_within(self, tracks: np.ndarray, gate: np.ndarray, lost: np.ndarray | None = None) -> np.ndarray:
        """Whether each of ``tracks`` has a rigid partner among the ``lost`` tracks (default: ``tracks``) close
        enough that its marker may show up inside the track's ``gate`` about where the track is expected."""
        others = tracks if lost is None else lost
        mate, _ = self._tracks.rigid(tracks, others)
        mate[tracks[:, None] == others[None]] = np.nan  # not its own mate
        return np.any(mate < 2.0 * gate[:, None], axis=1)  # NaN (not rigid) is never near

    def _ray_owners(self, rays: np.ndarray, cur: np.ndarray, time: float,
                    outside: np.ndarray | None) -> np.ndarray:
        """The rays ``(M, 6)`` given to the tracks not seen this frame, ``(T, 6)`` by track (NaN rows where none).

        A track expects its marker where it is predicted outside (a gap filler; gate ``reid_gate_mm``) or, within
        ``max_coast_s`` of its last sighting, where its constant-velocity coast takes it (gate growing with the
        unknown acceleration). A ray passing in front of the camera within that gate of the expected position may be
        the marker's, and is given to it when neither has another candidate: a line of sight crosses the whole
        volume, so where two markers could own a ray (or two rays a marker) none is given rather than a wrong one.
        """
        cfg = self.config
        out = np.full((len(cur), 6), np.nan)
        rows = np.flatnonzero(np.isfinite(rays).all(axis=1) & (norm(rays[:, 3:]) > 0))
        unseen = np.flatnonzero(np.isnan(cur[:, 0]))
        if not len(rows) or not len(unseen):
            return out
        dt = time - self._tracks.last[unseen]
        tracks = self._tracks
        expected = np.where((dt <= cfg.max_coast_s)[:, None], tracks.pos[unseen] + tracks.vel[unseen] * dt[:, None],
                            np.nan)
        gate = cfg.coast_gate(dt, self.rate)
        if outside is not None:
            known = np.zeros(len(unseen), bool)
            known[unseen < len(outside)] = np.isfinite(outside[unseen[unseen < len(outside)], 0])
            expected[known] = outside[unseen[known]]
            gate[known] = cfg.reid_gate_mm
        origin = rays[rows, :3]
        direction = rays[rows, 3:] / norm(rays[rows, 3:])[:, None]
        rel = expected[:, None] - origin[None]  # (U, R, 3)
        along = np.einsum("uri,ri->ur", rel, direction)
        miss = norm(rel - along[..., None] * direction[None])
        fits = (along > 0) & (miss < gate[:, None])  # NaN (nothing expected) fits nothing
        unique = fits & (fits.sum(axis=0) == 1)[None] & (fits.sum(axis=1) == 1)[:, None]
        ui, ri = np.nonzero(unique)
        out[unseen[ui]] = rays[rows[ri]]
        return out

    def _lost_predictions(self, lost: np.ndarray, cur: np.ndarray, time: float, outside: np.ndarray | None,
                          free: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Hypotheses ``(L, 2, 3)`` and gates ``(L, 2)`` for the tracks step 1 did not match (NaN where none).

        The first places the marker from its neighbours matched in this frame (or is the outside prediction, which
        replaces it); the second is a short constant-velocity coast whose gate grows with the unknown acceleration.
        Neighbours excel over long gaps and rigid neighbourhoods, the coast over a few frames among loose ones. The
        ``(L,)`` mask tells where the first is trusted at once: an outside prediction, or a placement whose misfit and
        spread (``place_marker``) are within ``instant_fit_mm`` (a rigid segment). A looser placement widens its gate by
        that doubt and is only used for points that have already lived ``confirm_frames`` frames, so a passing ghost
        cannot take the track; one doubtful by more than ``reid_gate_mm`` is not used at all. Only markers with a
        ``free`` point (one step 1 left) at distances from three of their seen neighbours that the snapshots have
        shown (give or take ``reid_gate_mm``) are placed: no other can be found, and most frames need no fit at all.
        """
        cfg = self.config
        tracks = self._tracks
        # an outside prediction replaces the placement, so only the others are placed
        pred, gate, given = _hypotheses(lost, np.empty((0, 3)) if outside is None else outside, tracks.pos, tracks.vel,
                                        tracks.last, time, cfg.max_coast_s, cfg.gate_mm, self.follow_mm,
                                        1.0 / self.rate, cfg.max_accel_mm_s2, cfg.reid_gate_mm)
        instant = given.copy()
        unknown = np.flatnonzero(~given)
        if len(free) and len(unknown):
            # each snapshot fitted to the neighbours matched in this frame; the best-fitting pose places the marker
            near = unknown[tracks.plausible(lost[unknown], cur, free).any(axis=1)]
            if len(near):
                anchors = tracks.anchors[lost[near]]
                now = np.where((anchors >= 0)[..., None], cur[anchors], np.nan)
                place, misfit, spread = place_marker(tracks.poses[lost[near]], now, tracks.anchor_w[lost[near]],
                                                     cfg.instant_fit_mm)
                doubt = np.fmax(misfit, spread)
                usable = doubt <= cfg.reid_gate_mm
                pred[near[usable], 0] = place[usable]
                gate[near, 0] += np.where(np.isnan(doubt), 0.0, doubt)
                instant[near] = doubt <= cfg.instant_fit_mm
        # a prediction on top of a marker already matched points at that marker, seen under another track: what lies
        # near it is a ghost or that marker, never this one
        _drop_near(pred, cur, cfg.gate_mm / 2)
        return pred, gate, instant

    def _lost_partners(self, lost: np.ndarray, cur: np.ndarray, z: np.ndarray,
                       near: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``rigid_signature`` of points ``z`` against ``lost`` tracks and their lost rigid partners, each placed on a
        tentative point of this frame.

        Markers of one body are often hidden together and come back a few frames apart, each with too few rigid
        partners seen to be recognised alone. A lost partner counts for a point when some other tentative point lies
        at their learnt distance from it and could be that partner: no rigid partner of the partner seen now rules
        it out. And the two must not fit the other way round as well: where the looser neighbours (``near``: the
        ``Tracks.plausible`` of ``lost`` and ``z``) allow the partner at the point and the track at the other point,
        their distance does not say which point is which (the simulated human's toe and fifth metatarsal markers, both
        lost with the heel, came back two frames apart, and the first took the toe's track on that distance alone).
        Returns ``(L, B)`` worst distance errors (as ``rigid_signature``) and counts of such partners.
        """
        tol = self.config.rigid_tolerance_mm
        mean, sd = self._tracks.rigid(lost, lost)
        np.fill_diagonal(mean, np.nan)
        broken, partners, _ = self._tracks.signature(lost, cur, self._tentative.pos)
        possible = (partners == 0) | (broken < 1.0)
        d = cdist(z, self._tentative.pos)
        error = np.abs(d[None, None] - mean[..., None, None]) / (tol + 3.0 * sd[..., None, None])
        error = np.where(possible[None, :, None], error, np.inf)  # (a, k, b, u)
        if (error < 1.0).any():  # the partner k could be the point b, and the track a the point u
            swapped = (near[None, :, :, None]
                       & self._tracks.plausible(lost, cur, self._tentative.pos)[:, None, None, :])
            error[swapped] = np.inf
        best = error.min(axis=3, initial=np.inf)
        fits = best < 1.0
        return np.where(fits, best, 0.0).max(axis=1, initial=0.0), fits.sum(axis=1)

    def _advance_tentatives(self, z: np.ndarray, free: np.ndarray, time: float) -> np.ndarray:
        """Carry tentative tracks on the ``free`` points of ``z`` (those no marker took) and start new ones on the rest.

        A tentative track missing one frame dies: a new marker must be tracked without a gap to be believed. Returns
        the row in ``z`` of each tentative track.
        """
        cfg = self.config
        tent = self._tentative
        if len(free) == 0 and len(tent.hits) == 0:  # most frames: nothing to carry on, nothing to start
            return free
        if len(tent.hits) == 0 or len(free) == 0:  # nothing carried on: every free point starts a tentative track
            tent.start(z[free], time, self.frame)
            return free
        dt = time - tent.time
        zf = z[free]
        # a point seen once has no velocity yet: its first step may be as long as the fastest marker moves
        ui, pi = match(_tentative_costs(tent.pos, tent.vel, tent.hits, zf, dt, cfg.gate_mm, self.follow_mm,
                                        cfg.max_speed_mm_s * dt))
        # the carried tracks, then new ones on the unclaimed points
        pos, vel, hits, order = _carry(tent.pos, tent.vel, tent.hits, zf, ui, pi, dt, cfg.velocity_smoothing)
        tent.step(pos, vel, hits, ui, time, self.frame)
        return free[order]

    def _owners(self, z: np.ndarray, cur: np.ndarray, lost: np.ndarray, pred: np.ndarray,
                gate: np.ndarray) -> np.ndarray:
        """The track each confirmed tentative point belongs to: a lost track that fits it, else a new one (-1: none).

        This is the thesis's merging of *Marker Sets*, done as the new set is born: a lost track fits when one of its
        hypotheses (``pred``, ``gate`` from ``_lost_predictions``; where its neighbours place nothing, the last
        position, for ``last_position_s`` only: a marker moves far in a few seconds) is within the gate, or when the
        point keeps its distances to two of the track's rigid partners seen now. With fewer seen, its lost partners
        placed on other tentative points (``_lost_partners``) and its looser neighbours (``Tracks.plausible``)
        complete the evidence: one partner seen and one more cue, or without any the neighbours and a lost partner
        (for ``last_position_s`` only: a track lost longer has often seen its marker come back under another track),
        as long as no other lost track fits the point that way, nor by its distance to a rigid partner seen now, and
        no marker seen now under a track never seen with this one fits it that loosely as well (``_seen_elsewhere``:
        its marker may have come back under that track, and a stale track only stands to take another's point). Once
        ``expected_markers`` tracks exist, the lost tracks are the only possible owners and the nearest wins without a
        gate; points left over stay tentative.
        """
        cfg = self.config
        pred = pred.copy()
        known = np.isfinite(pred[:, 0, 0])
        full = cfg.expected_markers is not None and len(self.labels) >= cfg.expected_markers
        recent = (self._time - self._tracks.last[lost] <= cfg.last_position_s) | full
        pred[~known & recent, 0] = self._tracks.pos[lost[~known & recent]]
        gate = gate.copy()
        gate[~known, 0] = cfg.reid_gate_mm
        li, ri = np.empty(0, np.intp), np.empty(0, np.intp)
        if len(lost):
            cost = gated_cost(pred, np.full(gate.shape, UNGATED_MM) if full else gate, z)
            broken, partners, violated = self._tracks.signature(lost, cur, z)
            near = self._tracks.plausible(lost, cur, z)
            lost_broken, helpers = self._lost_partners(lost, cur, z, near)
            worst = np.where(partners >= 2, broken, np.fmax(broken, lost_broken))
            # partners seen and lost, and the looser neighbours, for a point that fits no other lost track so
            pooled = (worst < 1.0) & np.where(partners >= 1, partners + helpers + near >= 2,
                                                near & (helpers >= 1) & recent[:, None])
            pooled[self._seen_elsewhere(lost, cur, pooled)] = False  # its marker may be in view under another track
            # another lost track that keeps its distance to a rigid partner as well makes the evidence ambiguous, the
            # looser cues notwithstanding: two markers of one segment often lie at one distance from a third
            rival = pooled | ((worst < 1.0) & (partners >= 1))
            fits = ((partners >= 2) & (broken < 1.0)) | (pooled & (rival.sum(axis=0) == 1))
            if not full:  # a coast alone does not tell a marker from a segment mate lost with it (``_reidentify``)
                alone = _on_coast_only(pred, gate, z) & (partners == 0) & (helpers == 0)
                cost = np.where(alone & self._mate_within(lost, gate[:, 1])[:, None], 0.0, cost)
            cost = np.where(fits, np.minimum(cost, worst - 1.0), cost)
            cost = screened(cost, broken, partners, violated)
            li, ri = match(cost)
        owners = np.full(len(z), -1, np.intp)
        owners[ri] = lost[li]
        room = len(z) if cfg.expected_markers is None else cfg.expected_markers - len(self.labels)
        for j in np.flatnonzero(owners < 0)[: max(room, 0)]:
            owners[j] = self._new_track()
        return owners

    def _seen_elsewhere(self, lost: np.ndarray, cur: np.ndarray, claims: np.ndarray) -> np.ndarray:
        """The indices, in ``lost``, of the tracks with a pooled claim (``claims``, lost tracks by points) that a
        marker seen now under another track fits as loosely as pooled cues ask (``_owners``): it keeps its distance
        to a rigid partner of the track seen now, the track's neighbours allow it, and the two tracks were never seen
        together (in the distance statistics). Such a track may be a marker that came back under a new track and is
        seen there now.

        Over long captures under the stress damage such stale tracks pile up: on 4800 frames of the simulated human,
        8 of the 107 points given to a lost track once tentative went to another marker's track, all on pooled cues,
        and for 5 of them the marker that track had held was then in view under another track. With the claims of
        such tracks void: 5 of 100, and 2 so."""
        rows = np.flatnonzero(claims.any(axis=1))
        seen = np.flatnonzero(np.isfinite(cur[:, 0]))
        if not len(rows) or not len(seen):
            return rows[:0]
        tracks = lost[rows]
        broken, partners, _ = self._tracks.signature(tracks, cur, cur[seen])
        near = self._tracks.plausible(tracks, cur, cur[seen])
        never = self._tracks.pair_n[np.ix_(tracks, seen)] == 0
        fits = (broken < 1.0) & (partners >= 1) & near & never
        return rows[fits.any(axis=1)]

    def _sure_owners(self, z: np.ndarray, hits: np.ndarray, cur: np.ndarray, lost: np.ndarray) -> np.ndarray:
        """The lost track each young tentative point (``hits`` frames old) surely belongs to, -1 where none: it keeps
        its distances to three of the track's rigid partners seen now (a point in space, up to a mirror image no
        marker of a body takes), or to two (a circle) once it has been followed for two frames, and no other point
        or lost track fits so. That is the evidence a confirmed point needs (``_owners``), asked of a point followed
        for two frames, or pinned in one: a ghost seldom lies on a circle of distances, and seldom lives two frames.
        A returning marker is then labelled from its first or second frame rather than after ``confirm_frames``."""
        if len(z) == 0 or len(lost) == 0:
            return np.full(len(z), -1, np.intp)
        broken, partners, _ = self._tracks.signature(lost, cur, z)
        return _sure_fits(broken, partners, hits, lost)

    def _adopt(self, ready: np.ndarray, owners: np.ndarray) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """Hand confirmed tentative tracks to their owners and return their earlier, so far unlabelled, points."""
        history: list[tuple[int, np.ndarray, np.ndarray]] = []
        tent = self._tentative
        done = owners >= 0
        for u, track in zip(ready[done], owners[done], strict=True):
            frames, pos = tent.points(int(u))
            tracks = self._tracks
            tracks.pos[track], tracks.vel[track], tracks.last[track] = tent.pos[u], tent.vel[u], tent.time
            tracks.streak[track] = tent.hits[u]
            history.append((int(track), frames[:-1], pos[:-1]))
        keep = np.ones(len(tent.hits), bool)
        keep[ready[done]] = False
        tent.keep(keep)
        return history

    def _new_track(self) -> int:
        """Append a confirmed track with empty state; labels are never reused."""
        t = len(self.labels)
        self.labels.append(f"M{t + 1:03d}")
        self._tracks.add()
        return t


@njit(cache=True)
def _finite_rows(points: np.ndarray) -> np.ndarray:  # pragma: no cover
    """The rows of ``points`` (M, 3) with no NaN or infinity."""
    rows = np.empty(len(points), np.intp)
    n = 0
    for i in range(len(points)):
        if finite(points[i]):
            rows[n] = i
            n += 1
    return rows[:n]


@njit(cache=True)
def _matched(tracks: np.ndarray, rows: np.ndarray, points: np.ndarray,
             n_tracks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """Step 1's assignment of ``points[rows]`` to ``tracks``: the tracks' positions (T, 3), NaN for the others
    (lost), the track that took each point (-1: none, free), and the lost tracks and free points."""
    cur = np.full((n_tracks, 3), np.nan)
    taken = np.full(len(points), -1, np.intp)
    for k in range(len(tracks)):
        cur[tracks[k]] = points[rows[k]]
        taken[rows[k]] = tracks[k]
    return cur, taken, np.flatnonzero(np.isnan(cur[:, 0])), np.flatnonzero(taken < 0)


@njit(cache=True)
def _step_one(pos: np.ndarray, vel: np.ndarray, last: np.ndarray, streak: np.ndarray, time: float, gate: float,
              follow: float, points: np.ndarray,
              n_tracks: int) -> tuple[np.ndarray, np.ndarray, bool, np.ndarray, np.ndarray, np.ndarray,
                                      np.ndarray]:  # pragma: no cover
    """Step 1 in one call where it is plain: the tracks followed and their costs (``_followed``), whether no track
    and no point has two admissible pairs (``assignment.unambiguous``: most frames), and then at once the pairs'
    outcome (``_matched``: positions, taken, lost, free; empty otherwise, for ``assignment.match`` to solve)."""
    live, cost = _followed(pos, vel, last, streak, time, gate, follow, points)
    rows, cols, unique = unambiguous(cost)
    if not unique:
        empty = np.empty(0, np.intp)
        return live, cost, False, np.empty((0, 3)), empty, empty, empty
    cur, taken, lost, free = _matched(live[rows], cols, points, n_tracks)
    return live, cost, True, cur, taken, lost, free


@njit(cache=True)
def _followed(pos: np.ndarray, vel: np.ndarray, last: np.ndarray, streak: np.ndarray, time: float, gate: float,
              follow: float, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """The tracks seen in the previous frame and the gated costs (``gated_cost``) of the ``points`` for them, each
    predicted at ``time`` at constant velocity, within its own gate (``own_gates``)."""
    live = np.flatnonzero(streak > 0)
    dt = time - last[live]
    pred = np.empty((len(live), 1, 3))
    for i, t in enumerate(live):
        for c in range(3):
            pred[i, 0, c] = pos[t, c] + vel[t, c] * dt[i]
    return live, gated_cost_compiled(pred, own_gates(gate, follow, vel[live], dt).reshape(-1, 1), points)


@njit(cache=True)
def own_gates(gate: float, follow: float, vel: np.ndarray, dt: np.ndarray) -> np.ndarray:  # pragma: no cover
    """The gates of tracks followed over ``dt`` (N,) at velocities ``vel`` (N, 3): ``gate``, each widened up to
    ``follow`` (``LabellerConfig.follow_gate``) by as far as the track moves in that time. Where frames are far apart
    a fast marker strays far from its constant-velocity course, while a marker at rest does not, and a wide gate would
    only reach its neighbours' points."""
    out = np.empty(len(dt))
    for i in range(len(dt)):
        step = np.sqrt(vel[i, 0] * vel[i, 0] + vel[i, 1] * vel[i, 1] + vel[i, 2] * vel[i, 2]) * dt[i]
        out[i] = max(gate, min(follow, step))
    return out


@njit(cache=True)
def _tentative_costs(pos: np.ndarray, vel: np.ndarray, hits: np.ndarray, points: np.ndarray, dt: float, gate: float,
                     follow: float, first_step: float) -> np.ndarray:  # pragma: no cover
    """The gated costs (``gated_cost``) of ``points`` for tentative tracks predicted ``dt`` on at constant velocity,
    each within its own gate (``own_gates``), that of a track seen once widened by ``first_step``."""
    pred = np.empty((len(pos), 1, 3))
    gates = own_gates(gate, follow, vel, np.full(len(pos), dt)).reshape(-1, 1)
    for i in range(len(pos)):
        for c in range(3):
            pred[i, 0, c] = pos[i, c] + vel[i, c] * dt
        if hits[i] == 1:
            gates[i, 0] = gate + first_step
    return gated_cost_compiled(pred, gates, points)


@njit(cache=True)
def _carry(pos: np.ndarray, vel: np.ndarray, hits: np.ndarray, points: np.ndarray, ui: np.ndarray, pi: np.ndarray,
           dt: float, smoothing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """Tentative tracks ``ui`` carried on to ``points[pi]`` (velocity measured over ``dt``, smoothed from their third
    frame), then new ones on the points left: positions, velocities, frames seen, and the row in ``points`` of each."""
    claimed = np.zeros(len(points), np.bool_)
    for p in pi:
        claimed[p] = True
    order = np.empty(len(points), np.intp)
    order[:len(pi)] = pi
    k = len(pi)
    for p in range(len(points)):
        if not claimed[p]:
            order[k] = p
            k += 1
    new_pos = np.empty((len(points), 3))
    new_vel = np.zeros((len(points), 3))
    new_hits = np.ones(len(points), np.int64)
    for k in range(len(points)):
        new_pos[k] = points[order[k]]
    for k in range(len(ui)):
        u = ui[k]
        for c in range(3):
            measured = (points[pi[k], c] - pos[u, c]) / dt
            new_vel[k, c] = vel[u, c] + smoothing * (measured - vel[u, c]) if hits[u] >= 2 else measured
        new_hits[k] = hits[u] + 1
    return new_pos, new_vel, new_hits, order


@njit(cache=True)
def _hypotheses(lost: np.ndarray, outside: np.ndarray, pos: np.ndarray, vel: np.ndarray, last: np.ndarray, time: float,
                max_coast_s: float, gate_mm: float, follow: float, frame_s: float, max_accel: float,
                reid_gate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """``Labeller._lost_predictions`` before the placement by neighbours: each ``lost`` track's first hypothesis its
    ``outside`` prediction where it has one (an empty array: none), its second its constant-velocity coast within
    ``max_coast_s``, with their gates (the coast's as ``LabellerConfig.coast_gate``, from the track's own gate in its
    last frame of ``frame_s``: ``own_gates``), and where the first is given."""
    pred = np.full((len(lost), 2, 3), np.nan)
    gate = np.full((len(lost), 2), reid_gate)
    own = own_gates(gate_mm, follow, vel[lost], np.full(len(lost), frame_s))
    given = np.zeros(len(lost), np.bool_)
    for i, t in enumerate(lost):
        if len(outside):
            given[i] = finite(outside[t])
            if given[i]:
                pred[i, 0] = outside[t]
        dt = time - last[t]
        if dt <= max_coast_s:
            for c in range(3):
                pred[i, 1, c] = pos[t, c] + vel[t, c] * dt
        gate[i, 1] = own[i] + 0.5 * max_accel * (dt * dt)
    return pred, gate, given


@njit(cache=True)
def _instant_costs(pred: np.ndarray, gate: np.ndarray, instant: np.ndarray,
                   points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """The lost tracks with a hypothesis to try now (``Labeller._reidentify``: the first, placed by neighbours, only
    where ``instant``) and the gated costs (``gated_cost``) of ``points`` for them."""
    now = pred.copy()
    for a in range(len(pred)):
        if not instant[a]:
            now[a, 0] = np.nan
    has = np.flatnonzero(np.isfinite(now[:, 0, 0]) | np.isfinite(now[:, 1, 0]))
    return has, gated_cost_compiled(now[has], gate[has], points)


@njit(cache=True)
def _sure_fits(broken: np.ndarray, partners: np.ndarray, hits: np.ndarray,
               tracks: np.ndarray) -> np.ndarray:  # pragma: no cover
    """For each point, the track (of ``tracks``, the rows of ``rigid_signature``'s ``broken`` and ``partners``
    ``(A, B)``) it surely fits (``Labeller._sure_owners``), -1 where none: no distance broken, to three partners or
    more (two once ``hits`` says the point was followed for two frames), and no other row or point fits so."""
    fits = np.zeros(broken.shape, np.bool_)
    rows = np.zeros(broken.shape[0], np.int64)
    cols = np.zeros(broken.shape[1], np.int64)
    for a in range(broken.shape[0]):
        for b in range(broken.shape[1]):
            fits[a, b] = broken[a, b] < 1.0 and partners[a, b] >= (2 if hits[b] >= 2 else 3)
            rows[a] += fits[a, b]
            cols[b] += fits[a, b]
    out = np.full(broken.shape[1], -1, np.intp)
    for a in range(broken.shape[0]):
        for b in range(broken.shape[1]):
            if fits[a, b] and rows[a] == 1 and cols[b] == 1:
                out[b] = tracks[a]
    return out


@njit(cache=True)
def _drop_near(hypotheses: np.ndarray, points: np.ndarray, radius: float) -> None:  # pragma: no cover
    """In place, NaN for each of the ``hypotheses`` (L, H, 3) closer than ``radius`` to one of ``points`` (T, 3) (NaN
    rows: none)."""
    for i in range(hypotheses.shape[0]):
        for h in range(hypotheses.shape[1]):
            for t in range(len(points)):
                if distance(hypotheses[i, h], points[t]) < radius:
                    hypotheses[i, h] = np.nan
                    break


def _on_coast_only(pred: np.ndarray, gate: np.ndarray, points: np.ndarray,
                   first: np.ndarray | None = None) -> np.ndarray:
    """``(A, B)``: the points inside the gate of a track's coast (its second hypothesis, ``_hypotheses``) and not
    inside that of its first, which counts only where ``first`` (default: for every track)."""
    firsts = gated_cost(pred[:, 0], gate[:, 0], points) < 0.0
    if first is not None:
        firsts &= first[:, None]
    return (gated_cost(pred[:, 1], gate[:, 1], points) < 0.0) & ~firsts


def _rival_fit(broken: np.ndarray, partners: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``(len(rows), B)``: for each of ``rows`` and point, how well the best other row of ``rigid_signature``'s
    ``broken`` and ``partners`` ``(A, B)`` fits the point by at least one rigid partner (``broken`` < 1), inf where
    no other does."""
    fit = np.where((partners >= 1) & (broken < 1.0), broken, np.inf)
    if len(fit) < 2:
        return np.full((len(rows), fit.shape[1]), np.inf)
    order = np.argsort(fit, axis=0)
    best, second = fit[order[0], np.arange(fit.shape[1])], fit[order[1], np.arange(fit.shape[1])]
    return np.where(order[0][None] == rows[:, None], second[None], best[None])
