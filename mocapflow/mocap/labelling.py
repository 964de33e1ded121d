"""Labelling of unlabelled marker clouds: one persistent identity per physical marker.

A passive optical tracker reports per frame an unordered set of points; occlusions remove some and reflections add
ghosts. Identities are carried from frame to frame as in Schoenauer (2007) section 3.3, with the predictive tracker
of its section 5.2 in place of nearest-point matching: each track predicts its position at constant velocity, and
the optimal one-to-one assignment inside a gate (``linear_sum_assignment``) replaces the thesis's greedy
smallest-distance-first pairing.

A track whose marker disappears is never dropped. The thesis finds the tracks of one physical marker by aligning
poses on a few nearby markers (its "local approach", 4-5 markers) and comparing positions (Kirk et al.'s *Marker Set*
distance, a minimum over pairs of poses); here that comparison runs online. Every track learns from the labelled data
which other tracks keep the steadiest distance to it (its neighbours, weighted by the inverse variance of that
distance) and keeps snapshots of itself with them. When its marker is lost, the snapshot whose neighbour distances
best match the current ones is fitted to the neighbours still visible and places the hidden marker, so a reappearing
point is matched back to its old track after seconds of occlusion. Once segments are known
(:meth:`Labeller.set_segments`) a track's neighbours are its segment mates: the snapshots are then the segment's rigid
marker layout. Three more cues help: a constant-velocity coast over short dropouts; the distances to the marker's
rigid partners (two of them hold a point to a circle: a segment reduced to two visible markers still recognises its
third; a point breaking the distances to all of them is ruled out, one breaking some must lie close to where the
marker is expected); positions predicted outside (a gap filler).

Body occlusions often hide several markers of one segment at once, which then come back a few frames apart. A
returning point keeps the distances to its lost partners that come back beside it, so rigid partners seen and lost
ones count together, and where none is seen the looser neighbours must at least allow the point; a point that fits
more than one lost marker so (a mirror-symmetric segment) is left to a new track rather than risk a swap.

A placement from a rigid neighbourhood re-identifies at once; a looser one (neighbours across a joint) only takes a
point that has lived ``confirm_frames`` frames, so that a passing ghost cannot steal the track. Points that match no
track start tentative tracks, which become markers (or re-identify a lost one) when they live ``confirm_frames``
frames; the rest, short-lived ghosts, are dropped. Offline, :func:`label_sequence` also merges what streaming could
not (the thesis's *Marker Set* merging, :func:`merge_tracks`) and drops tracks too short to be markers.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

from mocapflow.mocap.rigidfit import kabsch

_STATS_HZ = 60.0  # distance statistics need no more: markers' mutual distances change slowly
_VETO = 3.0  # a point breaking the distance to a rigid partner by this many tolerances cannot be that marker
_CANDIDATES = 3  # snapshots fitted per lost marker
_SD_FLOOR_MM = 1.0  # spread of a distance within a rigid body, from measurement noise: caps neighbour weights
_UNGATED_MM = 1e6  # a gate no capture volume reaches: "nearest wins" in an assignment


class LabellerConfig(BaseModel):
    """Tuning of the labeller; the defaults suit human capture at 100-240 Hz with markers 40 mm or more apart."""

    model_config = ConfigDict(extra="forbid")

    gate_mm: float = Field(30.0, gt=0, description="largest distance from a track's predicted position to the point it "
                           "takes, for a track seen in the previous frame")
    reid_gate_mm: float = Field(30.0, gt=0, description="largest distance from the position where a lost track's "
                                "neighbours place it (or given from outside) to the point that re-identifies it, "
                                "widened by the placement's doubt")
    instant_fit_mm: float = Field(5.0, ge=0, description="a lost marker placed by its neighbours this surely (RMS "
                                  "misfit and spread of candidate poses) is re-identified at once; looser placements "
                                  "only take points that have lived confirm_frames frames")
    max_coast_s: float = Field(0.1, ge=0, description="how long a lost track is also extrapolated at constant "
                               "velocity; after that only its neighbours can find it again")
    max_accel_mm_s2: float = Field(10_000.0, ge=0, description="acceleration bounding how fast a coasting track's gate "
                                   "grows: gate_mm + a t^2 / 2")
    max_speed_mm_s: float = Field(6_000.0, gt=0, description="fastest a marker moves; bounds the first step of a new "
                                  "point, which has no velocity yet")
    velocity_smoothing: float = Field(0.7, gt=0, le=1, description="weight of the newest frame-to-frame velocity in a "
                                      "track's velocity estimate")
    confirm_frames: int = Field(5, ge=1, description="consecutive frames a new point must be tracked before it is "
                                "accepted as a marker; shorter-lived points are ghosts")
    neighbours: int = Field(4, ge=3, description="neighbours that place a lost marker (the thesis uses 4-5)")
    neighbour_sd_mm: float = Field(100.0, gt=0, description="largest standard deviation of the distance to a marker "
                                   "for it to serve as a neighbour; each neighbour is weighted by 1/sd^2")
    rigid_sd_mm: float = Field(3.0, gt=0, description="largest standard deviation of the distance between two markers "
                               "for them to count as one rigid body")
    rigid_tolerance_mm: float = Field(5.0, gt=0, description="a point is a lost marker's when its distances to two or "
                                      "more of the marker's rigid partners are the learnt ones within this, plus 3 sd")
    rigid_min_s: float = Field(0.2, gt=0, description="time two markers must be seen together before their distance "
                               "statistics choose neighbours")
    reselect_s: float = Field(1.0, gt=0, description="how often neighbour sets are chosen again from the statistics")
    poses: int = Field(20, ge=1, description="snapshots of each marker with its neighbours kept to re-identify it")
    pose_interval_s: float = Field(0.1, gt=0, description="time between two snapshots of a marker and its neighbours")
    min_track_s: float = Field(0.5, ge=0, description="offline only: tracks seen for less than this in all, once "
                               "merged, are dropped as ghosts (the thesis drops Marker Sets under half a second)")
    expected_markers: int | None = Field(None, ge=1, description="number of physical markers, when known: at most "
                                         "this many tracks; beyond it new points can only re-identify lost tracks")


@dataclass
class LabelResult:
    """One frame's labelling.

    ``positions`` ``(T, 3)`` in track order, NaN where unseen; ``point_track`` the track of each input row, -1 for
    none. ``history`` lists the tracks confirmed or re-identified through a tentative track in this frame, as
    ``(track, frame_indices, positions)`` for the earlier frames (counted from 0 in calls to ``update``) in which their
    points were still unlabelled, so offline users can fill them in.
    """

    positions: np.ndarray
    point_track: np.ndarray
    history: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)
    rays: np.ndarray | None = None  # (T, 6) the single-camera ray taken by each track not seen as a point, NaN rows


def _norm(v: np.ndarray) -> np.ndarray:
    """Euclidean norm over the last axis (NaN in, NaN out), cheaper than ``np.linalg.norm`` on small batches."""
    return np.sqrt(np.einsum("...i,...i->...", v, v))


def _nanmedian(x: np.ndarray) -> np.ndarray:
    """Median over the last axis ignoring NaN (NaN when all are): ``np.nanmedian`` costs far more on small rows."""
    ordered = np.sort(x, axis=-1)  # NaN sort last
    n = np.isfinite(x).sum(axis=-1, keepdims=True)
    low = np.take_along_axis(ordered, np.maximum((n - 1) // 2, 0), axis=-1)[..., 0]
    high = np.take_along_axis(ordered, n // 2, axis=-1)[..., 0]
    return np.where(n[..., 0] > 0, (low + high) / 2, np.nan)


def _gated_cost(pred: np.ndarray, gate: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Cost ``(A, B)`` of giving each point to each track: ``d / gate - 1`` inside the track's gate, 0 outside.

    ``pred`` is ``(A, 3)``, or ``(A, H, 3)`` for tracks with several hypotheses (NaN where absent) of which the best
    counts; ``gate`` is ``(A,)`` or ``(A, H)``. With 0 for "unmatched" this is the classic assignment with a dummy
    option costing half a gate on each side, so a match is made only when it lowers the total distance.
    """
    if pred.ndim == 2:
        cost = cdist(pred, points) / gate[:, None]
    else:
        d = cdist(pred.reshape(-1, 3), points).reshape(*pred.shape[:2], -1) / gate[..., None]
        cost = np.fmin.reduce(d, axis=1)
        cost[np.isnan(cost)] = np.inf
    return np.minimum(cost - 1.0, 0.0)


def _match(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Optimal one-to-one assignment on a cost matrix where only negative entries are admissible pairs."""
    if cost.size == 0:
        return np.empty(0, np.intp), np.empty(0, np.intp)
    rows, cols = linear_sum_assignment(cost)
    keep = cost[rows, cols] < 0.0
    return rows[keep], cols[keep]


def _assign(pred: np.ndarray, gate: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Optimal one-to-one matching of tracks to points, each pair inside the track's gate (see ``_gated_cost``)."""
    if len(pred) == 0 or len(points) == 0:
        return np.empty(0, np.intp), np.empty(0, np.intp)
    return _match(_gated_cost(pred, gate, points))


def _signature(points: np.ndarray, partners: np.ndarray, mean: np.ndarray, sd: np.ndarray,
               tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How far points ``(B, 3)`` break each marker's distances to its rigid partners, how many partners count, and
    how many of those distances are broken.

    ``partners`` are the partners' positions, ``(P, 3)`` for all points or ``(B, P, 3)`` one set per point, NaN where
    unseen; ``mean``, ``sd`` ``(A, P)`` the learnt distances of each of A markers to each partner, NaN where a partner
    is not rigid with it. Returns ``(A, B)`` worst distance errors in units of ``tolerance + 3 sd`` (0 without
    partners), ``(A, B)`` partner counts and ``(A, B)`` counts of errors above 1. Two partners hold a point to a
    circle, three to a point: this recognises a marker whose rigid body has too few markers left to fit a pose (a
    two-marker remnant), and one partner is enough to rule a point out.
    """
    d = _norm(points[:, None] - partners) if partners.ndim == 3 else cdist(points, partners)
    error = np.abs(d[None] - mean[:, None]) / (tolerance + 3.0 * sd[:, None])
    valid = np.isfinite(error)
    return np.where(valid, error, 0.0).max(axis=2, initial=0.0), valid.sum(axis=2), (error > 1.0).sum(axis=2)


def _screened(cost: np.ndarray, broken: np.ndarray, partners: np.ndarray, violated: np.ndarray) -> np.ndarray:
    """Gated costs (``_gated_cost``) of points screened by their ``_signature``: a point cannot be the marker when it
    breaks the distance to a rigid partner by ``_VETO`` tolerances or those to all its partners, and it must lie
    within half the gate when it breaks some of them."""
    cost = np.where(broken > 1.0, np.minimum(2.0 * cost + 1.0, 0.0), cost)
    return np.where((broken > _VETO) | ((violated >= 1) & (violated == partners)), 0.0, cost)


def _place(poses: np.ndarray, now: np.ndarray, trust: np.ndarray,
           tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where a marker is now, from snapshots of it with its neighbours and the neighbours' current positions.

    ``poses`` ``(B, S, 1 + K, 3)``: S snapshots, row 0 the marker; ``now`` ``(B, K, 3)``, NaN where unseen; ``trust``
    ``(B, K)`` weights of the neighbours. The snapshots whose neighbour distances are closest to the current ones (3
    or more neighbours in common) are fitted rigidly to the neighbours, and the best fit places the marker: the
    minimum over poses of Kirk et al.'s *Marker Set* distance, on the thesis's local neighbourhood. Comparing
    distances first, which needs no fit, keeps the cost at ``_CANDIDATES`` fits per marker; fitting more than one
    rejects a mirror-image pose, which has the same distances. A neighbour whose distances to the others changed far
    more than theirs (the median change of its distances above three times the typical one, and above
    ``tolerance``) has moved relative to them and is left out, as long as three remain. Returns ``(B, 3)`` positions,
    ``(B,)`` weighted RMS misfits (NaN where no snapshot fits) and ``(B,)`` spreads: how far apart the candidates
    place the marker, which is large when the neighbours leave a turn undetermined (two rigid partners and loose
    others).
    """
    n = len(poses)
    common = np.isfinite(now[:, None, :, 0]) & np.isfinite(poses[..., 1:, 0]) & (trust[:, None] > 0)
    usable = (common.sum(axis=2) >= 3) & np.isfinite(poses[..., 0, 0])
    now_d = _norm(now[:, :, None] - now[:, None])
    then_d = _norm(poses[..., 1:, None, :] - poses[..., None, 1:, :])
    pair = common[..., :, None] & common[..., None, :]
    change = np.where(pair, np.abs(then_d - now_d[:, None]), 0.0).sum(axis=(2, 3))
    change = np.where(usable, change / np.maximum(pair.sum(axis=(2, 3)), 1), np.inf)
    order = np.argsort(change, axis=1)[:, :_CANDIDATES]
    bi, ci = np.nonzero(np.isfinite(np.take_along_axis(change, order, axis=1)))
    si = order[bi, ci]
    place = np.full((n, 3), np.nan)
    misfit = np.full(n, np.nan)
    spread = np.full(n, np.nan)
    if len(bi) == 0:
        return place, misfit, spread
    pose, target = poses[bi, si], now[bi]
    w = np.where(common[bi, si], trust[bi], 0.0)
    shift = np.abs(then_d[bi, si] - now_d[bi])
    shift = np.where((w[:, :, None] > 0) & (w[:, None, :] > 0), shift, np.nan)
    shift[:, np.arange(shift.shape[1]), np.arange(shift.shape[1])] = np.nan
    moved_by = _nanmedian(shift)
    typical = _nanmedian(moved_by)[:, None]
    out = (moved_by > np.maximum(3.0 * typical, tolerance)) & ((w > 0).sum(axis=1) >= 4)[:, None]
    w = np.where(((w > 0) & ~out).sum(axis=1, keepdims=True) >= 3, np.where(out, 0.0, w), w)
    use = (w > 0)[..., None]  # absent points may hold NaN
    r, t, _ = kabsch(np.where(use, pose[:, 1:], 0.0), np.where(use, target, 0.0), w)
    moved = np.einsum("bij,bnj->bni", r, pose) + t[:, None]
    sq = np.where(w > 0, ((moved[:, 1:] - target) ** 2).sum(axis=2), 0.0)
    fit = np.sqrt((w * sq).sum(axis=1) / w.sum(axis=1))
    # the best of each marker's candidates
    rank = np.full((n, _CANDIDATES), np.inf)
    rank[bi, ci] = fit
    pick = np.full((n, _CANDIDATES), -1)
    pick[bi, ci] = np.arange(len(bi))
    chosen = pick[np.arange(n), rank.argmin(axis=1)]
    found = chosen >= 0
    c = chosen[found]
    place[found] = moved[c, 0]
    misfit[found] = fit[c]
    at = np.full((n, _CANDIDATES, 3), np.nan)
    at[bi, ci] = moved[:, 0]
    spread[found] = np.nanmax(_norm(at[found] - place[found, None]), axis=1)
    return place, misfit, spread


class Labeller:
    """Streaming labeller: feed frames in time order to :meth:`update`; ``labels`` grows as markers are confirmed."""

    def __init__(self, config: LabellerConfig, rate: float) -> None:
        if rate <= 0:
            raise ValueError("rate must be positive")
        self.config = config
        self.rate = float(rate)
        self.labels: list[str] = []
        self.frame = 0
        self._time = -np.inf
        self._stats_every = max(1, round(self.rate / _STATS_HZ))
        k = config.neighbours
        # confirmed tracks: last observation, velocity, consecutive frames seen, neighbours, and a ring of snapshots
        # of each track with its neighbours (its row 0 is the track itself)
        self._pos = np.empty((0, 3))
        self._vel = np.empty((0, 3))
        self._last = np.empty(0)
        self._streak = np.empty(0, np.int64)
        self._anchors = np.empty((0, k), np.intp)
        self._anchor_w = np.empty((0, k))
        self._poses = np.empty((0, config.poses, k + 1, 3))
        self._pose_count = np.empty(0, np.int64)
        self._pose_time = np.empty(0)
        self._span = np.empty((0, k, 2))  # nearest and farthest each neighbour has been in the snapshots
        # running distance statistics between confirmed tracks (Welford), and declared segment mates
        self._pair_n = np.empty((0, 0))
        self._pair_mean = np.empty((0, 0))
        self._pair_m2 = np.empty((0, 0))
        self._mates = np.empty((0, 0), bool)
        self._next_select = config.rigid_min_s
        # tentative tracks and the points they have collected
        self._tpos = np.empty((0, 3))
        self._tvel = np.empty((0, 3))
        self._tlast = np.empty(0)
        self._thits = np.empty(0, np.int64)
        self._thist: list[list[tuple[int, np.ndarray]]] = []

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
        self._mates = mates
        width = max(self.config.neighbours, int(mates.sum(axis=1).max(initial=0)))
        extra = width - self._anchors.shape[1]
        if extra > 0:
            self._anchors = np.pad(self._anchors, ((0, 0), (0, extra)), constant_values=-1)
            self._anchor_w = np.pad(self._anchor_w, ((0, 0), (0, extra)))
            self._poses = np.pad(self._poses, ((0, 0), (0, 0), (0, extra), (0, 0)), constant_values=np.nan)
            self._span = np.concatenate([self._span, np.tile([np.inf, -np.inf], (len(self._span), extra, 1))], axis=1)
        self._next_select = -np.inf

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
        rows = np.flatnonzero(np.isfinite(pts).all(axis=1))
        z = pts[rows]
        taken = np.full(len(z), -1, np.intp)
        n_tracks = len(self.labels)
        if predictions is not None:
            predictions = np.asarray(predictions, dtype=float)
            if predictions.shape != (n_tracks, 3):
                raise ValueError(f"predictions must have shape ({n_tracks}, 3), got {predictions.shape}")
        cur = np.full((n_tracks, 3), np.nan)

        # 1. tracks seen in the previous frame: constant-velocity prediction, gated optimal assignment
        live = np.flatnonzero(self._streak > 0)
        pred = self._pos[live] + self._vel[live] * (time - self._last[live])[:, None]
        ti, pi = _assign(pred, np.full(len(live), cfg.gate_mm), z)
        cur[live[ti]] = z[pi]
        taken[pi] = live[ti]

        # 2. the others: re-identification from rigid neighbours or outside predictions, else a short coast
        lost = np.flatnonzero(np.isnan(cur[:, 0]))
        lost_pred, lost_gate, instant = self._lost_predictions(lost, cur, time, predictions, z[taken < 0])
        now_pred = lost_pred.copy()
        now_pred[~instant, 0] = np.nan
        has = np.flatnonzero(np.isfinite(now_pred[..., 0]).any(axis=1))
        free = np.flatnonzero(taken < 0)
        ti = pi = np.empty(0, np.intp)
        if len(has) and len(free):
            cost = _gated_cost(now_pred[has], lost_gate[has], z[free])
            broken, partners, violated = self._signature(lost[has], cur, z[free])
            cost = _screened(cost, broken, partners, violated)
            ti, pi = _match(cost)
        cur[lost[has[ti]]] = z[free[pi]]
        taken[free[pi]] = lost[has[ti]]
        self._observe(cur, time)

        # 3. tentative tracks on what is left; the long-lived ones become markers
        ready, ready_rows = self._advance_tentatives(z, taken, time)
        history: list[tuple[int, np.ndarray, np.ndarray]] = []
        if len(ready):
            still = np.isnan(cur[lost, 0])
            owners = self._owners(z[ready_rows], cur, lost[still], lost_pred[still], lost_gate[still])
            cur = np.vstack([cur, np.full((len(self.labels) - n_tracks, 3), np.nan)])
            history = self._adopt(ready, owners)
            cur[owners[owners >= 0]] = z[ready_rows[owners >= 0]]
            taken[ready_rows[owners >= 0]] = owners[owners >= 0]
        ray_out = None
        if rays is not None:
            rays = np.asarray(rays, dtype=float)
            if rays.shape != (len(pts), 6):
                raise ValueError(f"rays must have shape ({len(pts)}, 6), one per row of points, got {rays.shape}")
            ray_out = self._ray_owners(rays, cur, time, predictions)
        self._learn(cur, time)
        self.frame += 1
        point_track = np.full(len(pts), -1, np.intp)
        point_track[rows] = taken
        return LabelResult(positions=cur, point_track=point_track, history=history, rays=ray_out)

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
        rows = np.flatnonzero(np.isfinite(rays).all(axis=1) & (_norm(rays[:, 3:]) > 0))
        unseen = np.flatnonzero(np.isnan(cur[:, 0]))
        if not len(rows) or not len(unseen):
            return out
        dt = time - self._last[unseen]
        expected = np.where((dt <= cfg.max_coast_s)[:, None], self._pos[unseen] + self._vel[unseen] * dt[:, None],
                            np.nan)
        gate = cfg.gate_mm + 0.5 * cfg.max_accel_mm_s2 * dt**2
        if outside is not None:
            known = np.zeros(len(unseen), bool)
            known[unseen < len(outside)] = np.isfinite(outside[unseen[unseen < len(outside)], 0])
            expected[known] = outside[unseen[known]]
            gate[known] = cfg.reid_gate_mm
        origin = rays[rows, :3]
        direction = rays[rows, 3:] / _norm(rays[rows, 3:])[:, None]
        rel = expected[:, None] - origin[None]  # (U, R, 3)
        along = np.einsum("uri,ri->ur", rel, direction)
        miss = _norm(rel - along[..., None] * direction[None])
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
        spread (``_place``) are within ``instant_fit_mm`` (a rigid segment). A looser placement widens its gate by
        that doubt and is only used for points that have already lived ``confirm_frames`` frames, so a passing ghost
        cannot take the track; one doubtful by more than ``reid_gate_mm`` is not used at all. Only markers with a
        ``free`` point (one step 1 left) at distances from three of their seen neighbours that the snapshots have
        shown (give or take ``reid_gate_mm``) are placed: no other can be found, and most frames need no fit at all.
        """
        cfg = self.config
        pred = np.full((len(lost), 2, 3), np.nan)
        gate = np.full((len(lost), 2), cfg.reid_gate_mm)
        instant = np.zeros(len(lost), bool)
        if len(lost) == 0:
            return pred, gate, instant
        # each snapshot fitted to the neighbours matched in this frame; the best-fitting pose places the marker
        anchors = self._anchors[lost]
        now = np.where((anchors >= 0)[..., None], cur[anchors], np.nan)
        if len(free):
            near = np.flatnonzero(self._plausible(lost, cur, free).any(axis=1))
            place, misfit, spread = _place(self._poses[lost[near]], now[near], self._anchor_w[lost[near]],
                                           cfg.instant_fit_mm)
            doubt = np.fmax(misfit, spread)
            usable = doubt <= cfg.reid_gate_mm
            pred[near[usable], 0] = place[usable]
            gate[near, 0] += np.where(np.isnan(doubt), 0.0, doubt)
            instant[near] = doubt <= cfg.instant_fit_mm
        if outside is not None:
            given = np.isfinite(outside[lost]).all(axis=1)
            pred[given, 0] = outside[lost[given]]
            gate[given, 0] = cfg.reid_gate_mm
            instant |= given
        dt = time - self._last[lost]
        coast = dt <= cfg.max_coast_s
        pred[coast, 1] = self._pos[lost[coast]] + self._vel[lost[coast]] * dt[coast, None]
        gate[:, 1] = cfg.gate_mm + 0.5 * cfg.max_accel_mm_s2 * dt**2
        # a prediction on top of a marker already matched points at that marker, seen under another track: what lies
        # near it is a ghost or that marker, never this one
        matched = cur[np.isfinite(cur[:, 0])]
        if len(matched):
            near = cdist(pred.reshape(-1, 3), matched).min(axis=1).reshape(pred.shape[:2])
            pred[near < cfg.gate_mm / 2] = np.nan
        return pred, gate, instant

    def _plausible(self, tracks: np.ndarray, cur: np.ndarray, z: np.ndarray) -> np.ndarray:
        """``(T, B)``: where point ``z[b]`` can be the marker of ``tracks[t]``: its distances to three of the track's
        neighbours seen now (all, if fewer; one at least) are ones the snapshots have shown, give or take
        ``reid_gate_mm``."""
        anchors = self._anchors[tracks]
        now = np.where((anchors >= 0)[..., None], cur[anchors], np.nan)
        d = cdist(now.reshape(-1, 3), z).reshape(*now.shape[:2], len(z))
        span = self._span[tracks]
        fits = (d >= span[..., :1] - self.config.reid_gate_mm) & (d <= span[..., 1:] + self.config.reid_gate_mm)
        seen = np.isfinite(d[:, :, 0]).sum(axis=1)[:, None]
        return (fits.sum(axis=1) >= np.minimum(seen, 3)) & (seen >= 1)

    def _rigid(self, tracks: np.ndarray, others: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Learnt mean (NaN where the two are not one rigid body) and standard deviation of the distance between
        each of ``tracks`` and each of ``others``."""
        cfg = self.config
        block = np.ix_(tracks, others)
        n = self._pair_n[block]
        sd = np.sqrt(self._pair_m2[block] / np.maximum(n - 1.0, 1.0))
        rigid = (n >= cfg.rigid_min_s * self.rate / self._stats_every) & (sd <= cfg.rigid_sd_mm)
        return np.where(rigid, self._pair_mean[block], np.nan), sd

    def _signature(self, tracks: np.ndarray, cur: np.ndarray,
                   z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``_signature`` of points ``z`` against ``tracks`` and their rigid partners among this frame's matches."""
        seen = np.flatnonzero(np.isfinite(cur[:, 0]))
        mean, sd = self._rigid(tracks, seen)
        return _signature(z, cur[seen], mean, sd, self.config.rigid_tolerance_mm)

    def _lost_partners(self, lost: np.ndarray, cur: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``_signature`` of points ``z`` against ``lost`` tracks and their lost rigid partners, each placed on a
        tentative point of this frame.

        Markers of one body are often hidden together and come back a few frames apart, each with too few rigid
        partners seen to be recognised alone. A lost partner counts for a point when some other tentative point lies
        at their learnt distance from it and could be that partner: no rigid partner of the partner seen now rules
        it out. Returns ``(L, B)`` worst distance errors (as ``_signature``) and counts of such partners.
        """
        tol = self.config.rigid_tolerance_mm
        mean, sd = self._rigid(lost, lost)
        np.fill_diagonal(mean, np.nan)
        broken, partners, _ = self._signature(lost, cur, self._tpos)
        possible = (partners == 0) | (broken < 1.0)
        d = cdist(z, self._tpos)
        error = np.abs(d[None, None] - mean[..., None, None]) / (tol + 3.0 * sd[..., None, None])
        best = np.where(possible[None, :, None], error, np.inf).min(axis=3, initial=np.inf)
        fits = best < 1.0
        return np.where(fits, best, 0.0).max(axis=1, initial=0.0), fits.sum(axis=1)

    def _observe(self, cur: np.ndarray, time: float) -> None:
        """Update the kinematic state of confirmed tracks from this frame's matches."""
        seen = np.isfinite(cur[:, 0])
        m = np.flatnonzero(seen)
        dt = time - self._last[m]
        measured = (cur[m] - self._pos[m]) / dt[:, None]
        prev = self._streak[m]
        smooth = self._vel[m] + self.config.velocity_smoothing * (measured - self._vel[m])
        # a velocity measured across a long gap says little about the motion now
        across = np.where((dt <= self.config.max_coast_s)[:, None], measured, 0.0)
        self._vel[m] = np.where((prev >= 2)[:, None], smooth, np.where((prev == 1)[:, None], measured, across))
        self._pos[m] = cur[m]
        self._last[m] = time
        self._streak = np.where(seen, np.where(self._streak > 0, self._streak + 1, 1), 0)

    def _advance_tentatives(self, z: np.ndarray, taken: np.ndarray, time: float) -> tuple[np.ndarray, np.ndarray]:
        """Carry tentative tracks on the points no marker took and start new ones on the rest.

        A tentative track missing one frame dies: a new marker must be tracked without a gap to be believed. Returns
        the tentative tracks now old enough to confirm and their rows in ``z``.
        """
        cfg = self.config
        free = np.flatnonzero(taken < 0)
        if len(free) == 0 and len(self._tpos) == 0:
            return free, free
        pred = self._tpos + self._tvel * (time - self._tlast)[:, None]
        # a point seen once has no velocity yet: its first step may be as long as the fastest marker moves
        gate = cfg.gate_mm + np.where(self._thits == 1, cfg.max_speed_mm_s * (time - self._tlast), 0.0)
        ui, pi = _assign(pred, gate, z[free])
        zu = z[free[pi]]
        measured = (zu - self._tpos[ui]) / (time - self._tlast[ui])[:, None]
        smooth = self._tvel[ui] + cfg.velocity_smoothing * (measured - self._tvel[ui])
        vel = np.where((self._thits[ui] >= 2)[:, None], smooth, measured)
        kept = [self._thist[u] for u in ui]
        for points, p in zip(kept, zu, strict=True):
            points.append((self.frame, p))
            if len(points) > self.rate:  # only a tentative track held back by expected_markers grows this long
                del points[0]
        unclaimed = np.ones(len(free), bool)
        unclaimed[pi] = False
        fresh = np.flatnonzero(unclaimed)
        rows = np.concatenate([free[pi], free[fresh]])
        self._tpos = z[rows]
        self._tvel = np.concatenate([vel, np.zeros((len(fresh), 3))])
        self._tlast = np.full(len(rows), time)
        self._thits = np.concatenate([self._thits[ui] + 1, np.ones(len(fresh), np.int64)])
        self._thist = kept + [[(self.frame, p)] for p in z[free[fresh]]]
        ready = np.flatnonzero(self._thits >= cfg.confirm_frames)
        return ready, rows[ready]

    def _owners(self, z: np.ndarray, cur: np.ndarray, lost: np.ndarray, pred: np.ndarray,
                gate: np.ndarray) -> np.ndarray:
        """The track each confirmed tentative point belongs to: a lost track that fits it, else a new one (-1: none).

        This is the thesis's merging of *Marker Sets*, done as the new set is born: a lost track fits when one of its
        hypotheses (``pred``, ``gate`` from ``_lost_predictions``; the last position where its neighbours place
        nothing) is within the gate, or when the point keeps its distances to two of the track's rigid partners seen
        now. With fewer seen, its lost partners placed on other tentative points (``_lost_partners``) and its looser
        neighbours (``_plausible``) complete the evidence: one partner seen and one more cue, or without any the
        neighbours and a lost partner, as long as no other lost track fits the point that way. Once
        ``expected_markers`` tracks exist, the lost tracks are the only possible owners and the nearest wins without a
        gate; points left over stay tentative.
        """
        cfg = self.config
        pred = pred.copy()
        known = np.isfinite(pred[:, 0, 0])
        pred[~known, 0] = self._pos[lost[~known]]
        gate = gate.copy()
        gate[~known, 0] = cfg.reid_gate_mm
        full = cfg.expected_markers is not None and len(self.labels) >= cfg.expected_markers
        li, ri = np.empty(0, np.intp), np.empty(0, np.intp)
        if len(lost):
            cost = _gated_cost(pred, np.full(gate.shape, _UNGATED_MM) if full else gate, z)
            broken, partners, violated = self._signature(lost, cur, z)
            lost_broken, helpers = self._lost_partners(lost, cur, z)
            near = self._plausible(lost, cur, z)
            worst = np.where(partners >= 2, broken, np.fmax(broken, lost_broken))
            # partners seen and lost, and the looser neighbours, for a point that fits no other lost track so
            pooled = (worst < 1.0) & np.where(partners >= 1, partners + helpers + near >= 2, near & (helpers >= 1))
            fits = ((partners >= 2) & (broken < 1.0)) | (pooled & (pooled.sum(axis=0) == 1))
            cost = np.where(fits, np.minimum(cost, worst - 1.0), cost)
            cost = _screened(cost, broken, partners, violated)
            li, ri = _match(cost)
        owners = np.full(len(z), -1, np.intp)
        owners[ri] = lost[li]
        room = len(z) if cfg.expected_markers is None else cfg.expected_markers - len(self.labels)
        for j in np.flatnonzero(owners < 0)[: max(room, 0)]:
            owners[j] = self._new_track()
        return owners

    def _adopt(self, ready: np.ndarray, owners: np.ndarray) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """Hand confirmed tentative tracks to their owners and return their earlier, so far unlabelled, points."""
        history = []
        done = owners >= 0
        for u, track in zip(ready[done], owners[done], strict=True):
            frames = np.array([f for f, _ in self._thist[u]])
            pos = np.array([p for _, p in self._thist[u]])
            self._pos[track], self._vel[track], self._last[track] = self._tpos[u], self._tvel[u], self._tlast[u]
            self._streak[track] = self._thits[u]
            history.append((int(track), frames[:-1], pos[:-1]))
        keep = np.ones(len(self._thits), bool)
        keep[ready[done]] = False
        self._tpos, self._tvel, self._tlast, self._thits = (
            a[keep] for a in (self._tpos, self._tvel, self._tlast, self._thits))
        self._thist = [h for h, k in zip(self._thist, keep, strict=True) if k]
        return history

    def _new_track(self) -> int:
        """Append a confirmed track with empty state; labels are never reused."""
        t = len(self.labels)
        self.labels.append(f"M{t + 1:03d}")
        k = self._anchors.shape[1]
        self._pos = np.vstack([self._pos, np.full((1, 3), np.nan)])
        self._vel = np.vstack([self._vel, np.zeros((1, 3))])
        self._last = np.append(self._last, -np.inf)
        self._streak = np.append(self._streak, 0)
        self._anchors = np.vstack([self._anchors, np.full((1, k), -1, np.intp)])
        self._anchor_w = np.vstack([self._anchor_w, np.zeros((1, k))])
        self._poses = np.concatenate([self._poses, np.full((1, self.config.poses, k + 1, 3), np.nan)])
        self._pose_count = np.append(self._pose_count, 0)
        self._pose_time = np.append(self._pose_time, -np.inf)
        self._span = np.concatenate([self._span, np.tile([np.inf, -np.inf], (1, k, 1))])
        self._pair_n, self._pair_mean, self._pair_m2 = (
            np.pad(a, ((0, 1), (0, 1))) for a in (self._pair_n, self._pair_mean, self._pair_m2))
        self._mates = np.pad(self._mates, ((0, 1), (0, 1)))
        return t

    def _learn(self, cur: np.ndarray, time: float) -> None:
        """Learn from this frame's labelled points: distance statistics and neighbour sets (at up to ``_STATS_HZ``),
        and snapshots."""
        seen = np.flatnonzero(np.isfinite(cur[:, 0]))
        self._remember(seen, cur, time)
        if len(seen) < 2 or self.frame % self._stats_every:
            return
        block = np.ix_(seen, seen)
        d = cdist(cur[seen], cur[seen])
        n = self._pair_n[block] + 1.0
        mean = self._pair_mean[block]
        delta = d - mean
        mean = mean + delta / n
        self._pair_n[block], self._pair_mean[block] = n, mean
        self._pair_m2[block] += delta * (d - mean)
        if time >= self._next_select:
            self._select_neighbours(seen, time)
            self._next_select = time + self.config.reselect_s
        else:
            alone = seen[self._anchors[seen].max(axis=1) < 0]
            if len(alone):
                self._select_neighbours(alone, time)

    def _select_neighbours(self, tracks: np.ndarray, time: float) -> None:
        """Choose each track's neighbours: its segment mates if known, else the markers keeping the steadiest distance.

        Only markers seen lately qualify, so a marker lost for good stops being anyone's neighbour. A track whose
        neighbours change starts its snapshots afresh. Each neighbour is weighted by the inverse variance of its
        distance, so a loose one helps when the steady ones are hidden without spoiling the fit when they are not.
        """
        cfg = self.config
        n = self._pair_n[tracks]
        sd = np.sqrt(self._pair_m2[tracks] / np.maximum(n - 1.0, 1.0))
        recent = self._last >= time - cfg.reselect_s
        rigid = (n >= cfg.rigid_min_s * self.rate / self._stats_every) & (sd <= cfg.neighbour_sd_mm) & recent[None]
        rigid[np.arange(len(tracks)), tracks] = False
        # steadiest first, favouring near markers as the thesis does; current neighbours that still qualify stay, so
        # snapshots are not discarded for a marginal gain
        score = np.where(rigid, sd + 0.02 * self._pair_mean[tracks], np.inf)
        current = self._anchors[tracks]
        rows = np.repeat(np.arange(len(tracks)), current.shape[1])
        held = current.ravel() >= 0
        score[rows[held], current.ravel()[held]] -= 1e3
        mates = self._mates[tracks]
        enough = mates.sum(axis=1) >= 3
        score = np.where(mates, -1e4 + 1e-6 * self._pair_mean[tracks], np.where(enough[:, None], np.inf, score))
        width = self._anchors.shape[1]
        order = np.argsort(score, axis=1)[:, :width]
        chosen = np.where(np.isfinite(np.take_along_axis(score, order, axis=1)), order, -1)
        chosen = np.sort(chosen, axis=1)
        if chosen.shape[1] < width:
            chosen = np.pad(chosen, ((0, 0), (0, width - chosen.shape[1])), constant_values=-1)
        spread = np.take_along_axis(sd, np.maximum(chosen, 0), axis=1)
        self._anchor_w[tracks] = np.where(chosen >= 0, 1.0 / (spread**2 + _SD_FLOOR_MM**2), 0.0)
        changed = (chosen != self._anchors[tracks]).any(axis=1)
        moved = tracks[changed]
        self._anchors[moved] = chosen[changed]
        self._poses[moved] = np.nan
        self._pose_count[moved] = 0
        self._pose_time[moved] = -np.inf
        self._span[moved] = [np.inf, -np.inf]

    def _remember(self, seen: np.ndarray, cur: np.ndarray, time: float) -> None:
        """Snapshot, every ``pose_interval_s``, each seen track together with its neighbours (3 or more seen), and
        the range of its distances to each neighbour."""
        seen = seen[time - self._pose_time[seen] >= self.config.pose_interval_s]
        if len(seen) == 0:
            return
        anchors = self._anchors[seen]
        x = np.concatenate([cur[seen, None], np.where((anchors >= 0)[..., None], cur[anchors], np.nan)], axis=1)
        due = np.isfinite(x[:, 1:, 0]).sum(axis=1) >= 3
        tracks = seen[due]
        self._poses[tracks, self._pose_count[tracks] % self.config.poses] = x[due]
        self._pose_count[tracks] += 1
        self._pose_time[tracks] = time
        d = _norm(x[due, 1:] - x[due, :1])
        self._span[tracks, :, 0] = np.fmin(self._span[tracks, :, 0], d)
        self._span[tracks, :, 1] = np.fmax(self._span[tracks, :, 1], d)


def merge_tracks(tracks: np.ndarray, config: LabellerConfig | None = None) -> list[list[int]]:
    """Groups of tracks ``(F, T, 3)`` that are one physical marker: the thesis's merging of *Marker Sets*, offline.

    Online re-identification needs a lost track's neighbours to be known and seen when its marker comes back; a
    track lost before that, or whose neighbours were lost with it, comes back as a new track. Here every pair of
    tracks never seen together is compared as in Schoenauer (2007) section 3.3, on the thesis's local neighbourhood:
    snapshots of one track with its neighbours are fitted to those neighbours in the other track's frames, and the
    other track must lie within ``reid_gate_mm`` of the placed marker, or keep the distances to the first one's rigid
    partners; the median over frames decides (not the thesis's minimum, so that one coincidence cannot merge two
    markers). Pairs are merged greedily, best first, never joining tracks seen in the same frame, and the comparison
    is repeated on the merged tracks until nothing changes: merging the fragments of one marker gives its neighbours'
    fragments the partners they lacked.
    """
    cfg = config or LabellerConfig()
    groups = [[i] for i in range(tracks.shape[1])]
    while groups:
        joined = np.stack([np.fmax.reduce(tracks[:, g], axis=1) for g in groups], axis=1)
        seen = np.isfinite(joined[..., 0])
        overlap = seen.T.astype(np.int64) @ seen
        scored = []
        spreads: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for i, j in zip(*np.nonzero(np.triu(overlap == 0, 1)), strict=True):
            for k in (i, j):
                if k not in spreads:
                    spreads[k] = _distance_spread(joined, seen, k, cfg.confirm_frames)
            score = min(_set_score(joined, seen, i, j, spreads[i], cfg),
                        _set_score(joined, seen, j, i, spreads[j], cfg))
            if score < 1.0:
                scored.append((score, i, j))
        taken: set[int] = set()
        for _, i, j in sorted(scored):
            if i not in taken and j not in taken:
                groups[i] += groups[j]
                groups[j] = []
                taken |= {i, j}
        groups = [g for g in groups if g]
        if not taken:
            break
    return groups


def _distance_spread(tracks: np.ndarray, seen: np.ndarray, i: int, least: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation of track ``i``'s distance to every track over the frames they share; NaN where
    they share fewer than ``least`` frames (or than ``i`` has)."""
    d = _norm(tracks[seen[:, i], i, None] - tracks[seen[:, i]])
    count = np.isfinite(d).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.nansum(d, axis=0) / count
        sd = np.sqrt(np.nansum((d - mean) ** 2, axis=0) / count)
    few = count < min(len(d), least)
    mean[few] = sd[few] = np.nan
    return mean, sd


def _set_score(tracks: np.ndarray, seen: np.ndarray, i: int, j: int, spread: tuple[np.ndarray, np.ndarray],
               cfg: LabellerConfig) -> float:
    """How well track ``j`` fits marker ``i`` in ``j``'s frames, below 1 when it is the same marker.

    The median over (at most ``poses``) frames of the smaller of: the distance to where ``i``'s neighbours place it,
    in units of ``reid_gate_mm``; the worst error of its distances to ``i``'s rigid partners (two or more seen), in
    units of their tolerance (``_signature``).
    """
    fi, fj = np.flatnonzero(seen[:, i]), np.flatnonzero(seen[:, j])
    mean, sd = spread
    known = np.isfinite(sd)
    known[[i, j]] = False
    b = _evenly(fj, cfg.poses)
    partners = np.flatnonzero(known & (sd <= cfg.rigid_sd_mm))
    broken, count, _ = _signature(tracks[b, j], tracks[b][:, partners], mean[None, partners], sd[None, partners],
                                  cfg.rigid_tolerance_mm)
    signature = np.where(count[0] >= 2, broken[0], np.inf)
    score = np.where(known, sd + 0.02 * mean, np.inf)
    score[~(sd <= cfg.neighbour_sd_mm) | (seen[fj].sum(axis=0) < 3)] = np.inf
    nb = np.argsort(score)[: cfg.neighbours]
    nb = nb[np.isfinite(score[nb])]
    placed = np.full(len(b), np.inf)
    a = _evenly(fi[seen[fi][:, nb].sum(axis=1) >= 3], cfg.poses)
    if len(nb) >= 3 and len(a):
        poses = np.concatenate([tracks[a, i, None], tracks[a][:, nb]], axis=1)
        trust = np.broadcast_to(1.0 / (sd[nb] ** 2 + _SD_FLOOR_MM**2), (len(b), len(nb)))
        place, _, _ = _place(np.broadcast_to(poses, (len(b), *poses.shape)), tracks[b][:, nb], trust,
                             cfg.instant_fit_mm)
        err = _norm(place - tracks[b, j]) / cfg.reid_gate_mm
        placed = np.where(np.isfinite(err), err, np.inf)
    best = np.minimum(placed, signature)
    best = best[np.isfinite(best)]
    return float(np.median(best)) if len(best) else np.inf


def _evenly(frames: np.ndarray, count: int) -> np.ndarray:
    """At most ``count`` of ``frames``, evenly spread."""
    if len(frames) <= count:
        return frames
    return frames[np.linspace(0, len(frames) - 1, count).round().astype(int)]


def label_sequence(frames: Iterable[np.ndarray], rate: float,
                   config: LabellerConfig | None = None) -> tuple[np.ndarray, list[str]]:
    """Label a whole recording of point clouds: ``(F, T, 3)`` trajectories of the ``T`` markers found, and labels.

    Knowing the whole recording allows more than streaming: points a track collected while still tentative are
    filled in, tracks of one marker are merged (:func:`merge_tracks`), and tracks seen for less than ``min_track_s``
    in all are dropped. Markers are labelled ``M001``... in order of first appearance.
    """
    cfg = config or LabellerConfig()
    labeller = Labeller(cfg, rate)
    rows: list[np.ndarray] = []
    late: list[tuple[int, np.ndarray, np.ndarray]] = []
    for i, points in enumerate(frames):
        result = labeller.update(points, i / rate)
        rows.append(result.positions)
        late += result.history
    tracks = np.full((len(rows), len(labeller.labels), 3), np.nan)
    for i, row in enumerate(rows):
        tracks[i, : len(row)] = row
    for track, idx, pos in late:
        tracks[idx, track] = pos
    markers = []
    for group in merge_tracks(tracks, cfg):
        merged = np.fmax.reduce(tracks[:, group], axis=1)  # the tracks of a group never share a frame
        if np.isfinite(merged[:, 0]).sum() >= cfg.min_track_s * rate:
            markers.append(merged)
    markers.sort(key=lambda m: np.flatnonzero(np.isfinite(m[:, 0]))[0])
    out = np.stack(markers, axis=1) if markers else np.full((len(rows), 0, 3), np.nan)
    return out, [f"M{k + 1:03d}" for k in range(out.shape[1])]


@dataclass
class LabellingScore:
    """How a labelling compares with the true identities of its points.

    Each track stands for the true marker it most often holds (majority vote). ``accuracy`` is the share of real
    points given the track that stands for their marker (so unlabelled points count as wrong); ``swaps`` counts the
    times a track moves from one true marker to another; ``fragments`` the tracks beyond one per true marker.
    """

    accuracy: float
    assigned: float
    swaps: int
    ghosts_rejected: float
    tracks: int
    ghost_tracks: int
    fragments: int
    markers_found: int
    markers_true: int

    def summary(self) -> str:
        """One line for reports and benchmarks."""
        return (f"accuracy {100 * self.accuracy:.3f} %, assigned {100 * self.assigned:.3f} %, swaps {self.swaps}, "
                f"ghosts rejected {100 * self.ghosts_rejected:.2f} %, {self.tracks} tracks for "
                f"{self.markers_found}/{self.markers_true} markers ({self.fragments} fragments, "
                f"{self.ghost_tracks} ghost tracks)")


def score_labelling(tracks: np.ndarray, points: Sequence[np.ndarray], identity: Sequence[np.ndarray],
                    markers: int) -> LabellingScore:
    """Score trajectories ``(F, T, 3)`` labelled from ``points`` (per frame ``(M, 3)``) against ``identity``.

    ``identity`` gives per frame the true marker index of each row of ``points``, -1 for a ghost; ``markers`` is the
    number of true markers. A labelled position is traced back to the input row it was copied from.
    """
    n_frames, n_tracks, _ = tracks.shape
    held = np.full((n_frames, n_tracks), -2)  # true marker held by each track; -1 ghost, -2 nothing
    real = ghosts = 0
    for f in range(n_frames):
        rows = np.asarray(points[f], dtype=float).reshape(-1, 3)
        ids = np.asarray(identity[f])
        present = np.isfinite(rows).all(axis=1)
        real += int((present & (ids >= 0)).sum())
        ghosts += int((present & (ids < 0)).sum())
        on = np.flatnonzero(np.isfinite(tracks[f, :, 0]))
        if len(on) == 0:
            continue
        d = cdist(tracks[f, on], np.where(present[:, None], rows, np.inf))
        source = d.argmin(axis=1)
        if (d[np.arange(len(on)), source] > 1e-6).any():
            raise ValueError(f"frame {f}: a labelled position is not one of the input points")
        held[f, on] = ids[source]
    majority = np.array([np.bincount(h[h >= 0], minlength=markers).argmax() if (h >= 0).any() else -1
                         for h in held.T], dtype=int)
    right = int(((held >= 0) & (held == majority[None])).sum())
    swaps = sum(int(np.count_nonzero(np.diff(h[h >= 0]))) for h in held.T)
    found = majority[majority >= 0]
    return LabellingScore(
        accuracy=right / max(real, 1), assigned=int((held >= 0).sum()) / max(real, 1), swaps=swaps,
        ghosts_rejected=1.0 - int((held == -1).sum()) / max(ghosts, 1), tracks=n_tracks,
        ghost_tracks=int((majority < 0).sum()), fragments=len(found) - len(set(found.tolist())),
        markers_found=len(set(found.tolist())), markers_true=markers,
    )


def unlabel(positions: np.ndarray, rate: float, seed: int, gaps_per_s: float = 0.05, long_fraction: float = 0.3,
            ghosts: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A labelled recording ``(F, N, 3)`` as a passive tracker would report it, to test labelling against truth.

    Adds occlusions (``gaps_per_s`` per marker per second; a ``long_fraction`` of them 0.5-2 s long, the others 1-9
    frames), ghost points (Poisson, ``ghosts`` new per frame, each living 1-3 frames, 20-300 mm from a random
    marker, with 0.5 mm jitter) and shuffles the rows of every frame. Returns points ``(F, W, 3)`` padded with NaN
    and identity ``(F, W)``: the true marker index of each row, -1 for ghosts and padding.
    """
    rng = np.random.default_rng(seed)
    n_frames, n_markers, _ = positions.shape
    seen = np.isfinite(positions).all(axis=2)
    for marker in range(n_markers):
        for _ in range(rng.poisson(gaps_per_s * n_frames / rate)):
            long = rng.random() < long_fraction
            length = int(rng.uniform(0.5, 2.0) * rate) if long else int(rng.integers(1, 10))
            start = int(rng.integers(0, n_frames))
            seen[start:start + length, marker] = False
    clouds: list[np.ndarray] = []
    owners: list[np.ndarray] = []
    alive: list[tuple[int, np.ndarray]] = []  # (last frame, position) of each ghost
    for f in range(n_frames):
        visible = np.flatnonzero(seen[f])
        for _ in range(rng.poisson(ghosts) if len(visible) else 0):
            direction = rng.standard_normal(3)
            centre = positions[f, rng.choice(visible)] + direction / np.linalg.norm(direction) * rng.uniform(20, 300)
            alive.append((f + int(rng.integers(0, 3)), centre))
        alive = [(last, c) for last, c in alive if last >= f]
        ghost_pts = np.array([c for _, c in alive]).reshape(-1, 3) + rng.normal(0.0, 0.5, (len(alive), 3))
        cloud = np.concatenate([positions[f, visible], ghost_pts])
        owner = np.concatenate([visible, np.full(len(alive), -1)])
        order = rng.permutation(len(cloud))
        clouds.append(cloud[order])
        owners.append(owner[order])
    width = max((len(c) for c in clouds), default=0)
    points = np.full((n_frames, width, 3), np.nan)
    identity = np.full((n_frames, width), -1)
    for f, (cloud, owner) in enumerate(zip(clouds, owners, strict=True)):
        points[f, : len(cloud)] = cloud
        identity[f, : len(owner)] = owner
    return points, identity
