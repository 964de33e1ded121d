"""The tracks of the labeller: the confirmed ones and what they learn from labelled frames (kinematic state, running
distance statistics between tracks, neighbour sets and snapshots of each track with its neighbours), and the
tentative ones, points not yet believed to be markers."""

from __future__ import annotations

from collections import deque

import numpy as np
from numba import njit

from mocapflow.mocap.labelling.assignment import distance, rigid_signature_compiled
from mocapflow.mocap.labelling.config import SD_FLOOR_MM, STATS_HZ, LabellerConfig


class Tracks:
    """Per confirmed track, in track order: last observation, velocity, consecutive frames seen, neighbours and a
    ring of snapshots of the track with its neighbours (row 0 the track itself); per pair of tracks, running distance
    statistics (Welford) and whether they are declared segment mates. ``add`` grows every array by one track."""

    def __init__(self, config: LabellerConfig, rate: float) -> None:
        self.config = config
        self.rate = rate
        self.stats_every = max(1, round(rate / STATS_HZ))
        self.rigid_samples = config.rigid_min_s * rate / self.stats_every  # statistics samples rigidity needs
        k = config.neighbours
        self.pos = np.empty((0, 3))
        self.vel = np.empty((0, 3))
        self.last = np.empty(0)
        self.streak = np.empty(0, np.int64)
        self.anchors = np.empty((0, k), np.intp)
        self.anchor_w = np.empty((0, k))
        self.poses = np.empty((0, config.poses, k + 1, 3))
        self.pose_count = np.empty(0, np.int64)
        self.pose_time = np.empty(0)
        self.span = np.empty((0, k, 2))  # nearest and farthest each neighbour has been in the snapshots
        self.pair_n = np.empty((0, 0))
        self.pair_mean = np.empty((0, 0))
        self.pair_m2 = np.empty((0, 0))
        self.mates = np.empty((0, 0), bool)
        self.next_select = config.rigid_min_s

    def add(self) -> None:
        """Append a track with empty state."""
        k = self.anchors.shape[1]
        self.pos = np.vstack([self.pos, np.full((1, 3), np.nan)])
        self.vel = np.vstack([self.vel, np.zeros((1, 3))])
        self.last = np.append(self.last, -np.inf)
        self.streak = np.append(self.streak, 0)
        self.anchors = np.vstack([self.anchors, np.full((1, k), -1, np.intp)])
        self.anchor_w = np.vstack([self.anchor_w, np.zeros((1, k))])
        self.poses = np.concatenate([self.poses, np.full((1, self.config.poses, k + 1, 3), np.nan)])
        self.pose_count = np.append(self.pose_count, 0)
        self.pose_time = np.append(self.pose_time, -np.inf)
        self.span = np.concatenate([self.span, np.tile([np.inf, -np.inf], (1, k, 1))])
        self.pair_n, self.pair_mean, self.pair_m2 = (
            np.pad(a, ((0, 1), (0, 1))) for a in (self.pair_n, self.pair_mean, self.pair_m2))
        self.mates = np.pad(self.mates, ((0, 1), (0, 1)))

    def set_mates(self, mates: np.ndarray) -> None:
        """Declare segment mates ``(T, T)`` bool; neighbour sets widen to hold them and are chosen again."""
        self.mates = mates
        width = max(self.config.neighbours, int(mates.sum(axis=1).max(initial=0)))
        extra = width - self.anchors.shape[1]
        if extra > 0:
            self.anchors = np.pad(self.anchors, ((0, 0), (0, extra)), constant_values=-1)
            self.anchor_w = np.pad(self.anchor_w, ((0, 0), (0, extra)))
            self.poses = np.pad(self.poses, ((0, 0), (0, 0), (0, extra), (0, 0)), constant_values=np.nan)
            self.span = np.concatenate([self.span, np.tile([np.inf, -np.inf], (len(self.span), extra, 1))], axis=1)
        self.next_select = -np.inf

    def forget_cues(self) -> None:
        """Forget the snapshots and distance statistics learnt so far (the kinematic state stays): cues learnt before
        every marker was lost at once could hand a mirror-image marker to the wrong track."""
        self.poses[:] = np.nan
        self.pose_count[:] = 0
        self.pose_time[:] = -np.inf
        self.pair_n[:], self.pair_mean[:], self.pair_m2[:] = 0.0, 0.0, 0.0
        self.next_select = -np.inf

    def plausible(self, tracks: np.ndarray, cur: np.ndarray, z: np.ndarray) -> np.ndarray:
        """``(T, B)``: where point ``z[b]`` can be the marker of ``tracks[t]``: its distances to three of the track's
        neighbours seen now (all, if fewer; one at least) are ones the snapshots have shown, give or take
        ``reid_gate_mm``."""
        return _plausible(self.anchors, self.span, tracks, cur, z, self.config.reid_gate_mm)

    def rigid(self, tracks: np.ndarray, others: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Learnt mean (NaN where the two are not one rigid body) and standard deviation of the distance between
        each of ``tracks`` and each of ``others``."""
        return _rigid(self.pair_n, self.pair_mean, self.pair_m2, tracks, others, self.rigid_samples,
                      self.config.rigid_sd_mm)

    def signature(self, tracks: np.ndarray, cur: np.ndarray,
                  z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``rigid_signature`` of points ``z`` against ``tracks`` and their rigid partners (``rigid``) among the tracks
        seen in ``cur`` (NaN rows: not seen)."""
        cfg = self.config
        return _signature_now(self.pair_n, self.pair_mean, self.pair_m2, tracks, cur, z, self.rigid_samples,
                              cfg.rigid_sd_mm, cfg.rigid_tolerance_mm)

    def observe(self, cur: np.ndarray, time: float) -> None:
        """Update the kinematic state of confirmed tracks from this frame's matches."""
        observed(cur, time, self.pos, self.vel, self.last, self.streak, self.config.velocity_smoothing,
                 self.config.max_coast_s)

    def learn(self, cur: np.ndarray, time: float, frame: int) -> None:
        """Learn from this frame's labelled points: distance statistics and neighbour sets (at up to ``STATS_HZ``),
        and snapshots."""
        seen = np.isfinite(cur[:, 0]).nonzero()[0]
        self._remember(seen, cur, time)
        if len(seen) < 2 or frame % self.stats_every:
            return
        _accumulate(seen, cur, self.pair_n, self.pair_mean, self.pair_m2)
        if time >= self.next_select:
            self._select_neighbours(seen, time)
            self.next_select = time + self.config.reselect_s
        else:
            alone = seen[self.anchors[seen].max(axis=1) < 0]
            if len(alone):
                self._select_neighbours(alone, time)

    def _select_neighbours(self, tracks: np.ndarray, time: float) -> None:
        """Choose each track's neighbours: its segment mates if known, else the markers keeping the steadiest distance.

        Only markers seen lately qualify, so a marker lost for good stops being anyone's neighbour. A track whose
        neighbours change starts its snapshots afresh. Each neighbour is weighted by the inverse variance of its
        distance, so a loose one helps when the steady ones are hidden without spoiling the fit when they are not.
        """
        cfg = self.config
        n = self.pair_n[tracks]
        sd = np.sqrt(self.pair_m2[tracks] / np.maximum(n - 1.0, 1.0))
        recent = self.last >= time - cfg.reselect_s
        rigid = (n >= self.rigid_samples) & (sd <= cfg.neighbour_sd_mm) & recent[None]
        rigid[np.arange(len(tracks)), tracks] = False
        # steadiest first, favouring near markers as the thesis does; current neighbours that still qualify stay, so
        # snapshots are not discarded for a marginal gain
        score = np.where(rigid, sd + 0.02 * self.pair_mean[tracks], np.inf)
        current = self.anchors[tracks]
        rows = np.repeat(np.arange(len(tracks)), current.shape[1])
        held = current.ravel() >= 0
        score[rows[held], current.ravel()[held]] -= 1e3
        mates = self.mates[tracks]
        enough = mates.sum(axis=1) >= 3
        score = np.where(mates, -1e4 + 1e-6 * self.pair_mean[tracks], np.where(enough[:, None], np.inf, score))
        width = self.anchors.shape[1]
        order = np.argsort(score, axis=1)[:, :width]
        chosen = np.where(np.isfinite(np.take_along_axis(score, order, axis=1)), order, -1)
        chosen = np.sort(chosen, axis=1)
        if chosen.shape[1] < width:
            chosen = np.pad(chosen, ((0, 0), (0, width - chosen.shape[1])), constant_values=-1)
        spread = np.take_along_axis(sd, np.maximum(chosen, 0), axis=1)
        self.anchor_w[tracks] = np.where(chosen >= 0, 1.0 / (spread**2 + SD_FLOOR_MM**2), 0.0)
        changed = (chosen != self.anchors[tracks]).any(axis=1)
        moved = tracks[changed]
        self.anchors[moved] = chosen[changed]
        self.poses[moved] = np.nan
        self.pose_count[moved] = 0
        self.pose_time[moved] = -np.inf
        self.span[moved] = [np.inf, -np.inf]

    def _remember(self, seen: np.ndarray, cur: np.ndarray, time: float) -> None:
        """Snapshot, every ``pose_interval_s``, each seen track together with its neighbours (3 or more seen), and
        the range of its distances to each neighbour."""
        _remember(seen, cur, time, self.config.pose_interval_s, self.anchors, self.poses, self.pose_count,
                  self.pose_time, self.span)


@njit(cache=True)
def _accumulate(seen: np.ndarray, cur: np.ndarray, pair_n: np.ndarray, pair_mean: np.ndarray,
                pair_m2: np.ndarray) -> None:  # pragma: no cover
    """In place, the running statistics (Welford: count, mean, sum of squared deviations) of the distance of every
    pair of the ``seen`` tracks, positions ``cur``, a track with itself included."""
    for a in seen:
        for b in seen:
            d = distance(cur[a], cur[b])
            n = pair_n[a, b] + 1.0
            delta = d - pair_mean[a, b]
            mean = pair_mean[a, b] + delta / n
            pair_n[a, b], pair_mean[a, b] = n, mean
            pair_m2[a, b] += delta * (d - mean)


@njit(cache=True)
def _plausible(anchors: np.ndarray, span: np.ndarray, tracks: np.ndarray, cur: np.ndarray, z: np.ndarray,
               gate: float) -> np.ndarray:  # pragma: no cover
    """``Tracks.plausible``, track by track: it runs in most frames where a marker is lost."""
    out = np.zeros((len(tracks), len(z)), dtype=np.bool_)
    for i in range(len(tracks)):
        neighbours = anchors[tracks[i]]
        seen = 0
        for k in range(len(neighbours)):
            if neighbours[k] >= 0 and np.isfinite(cur[neighbours[k], 0]):
                seen += 1
        if seen == 0:
            continue
        for b in range(len(z)):
            fits = 0
            for k in range(len(neighbours)):
                if neighbours[k] >= 0:
                    d = distance(cur[neighbours[k]], z[b])
                    lo, hi = span[tracks[i], k, 0], span[tracks[i], k, 1]
                    if d >= lo - gate and d <= hi + gate:
                        fits += 1
            out[i, b] = fits >= min(seen, 3)
    return out


@njit(cache=True)
def _rigid(pair_n: np.ndarray, pair_mean: np.ndarray, pair_m2: np.ndarray, tracks: np.ndarray, others: np.ndarray,
           least: float, most_sd: float) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """``Tracks.rigid`` on the pair statistics: rigid where seen together in ``least`` statistics samples or more
    with a spread of ``most_sd`` or less."""
    mean = np.empty((len(tracks), len(others)))
    sd = np.empty((len(tracks), len(others)))
    for i in range(len(tracks)):
        for j in range(len(others)):
            n = pair_n[tracks[i], others[j]]
            sd[i, j] = np.sqrt(pair_m2[tracks[i], others[j]] / max(n - 1.0, 1.0))
            mean[i, j] = pair_mean[tracks[i], others[j]] if n >= least and sd[i, j] <= most_sd else np.nan
    return mean, sd


@njit(cache=True)
def _signature_now(pair_n: np.ndarray, pair_mean: np.ndarray, pair_m2: np.ndarray, tracks: np.ndarray,
                   cur: np.ndarray, z: np.ndarray, least: float, most_sd: float,
                   tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """``Tracks.signature`` on the pair statistics, in one compiled call: the labeller asks for it several times a
    frame."""
    seen = np.flatnonzero(np.isfinite(cur[:, 0]))
    mean, sd = _rigid(pair_n, pair_mean, pair_m2, tracks, seen, least, most_sd)
    partners = np.empty((len(z), len(seen), 3))
    for b in range(len(z)):
        for p in range(len(seen)):
            partners[b, p] = cur[seen[p]]
    return rigid_signature_compiled(z, partners, mean, sd, tolerance)


@njit(cache=True)
def observed(cur: np.ndarray, time: float, pos: np.ndarray, vel: np.ndarray, last: np.ndarray, streak: np.ndarray,
            smoothing: float, max_coast_s: float) -> None:  # pragma: no cover
    """Take the tracks (or markers) seen in ``cur`` (NaN rows: not seen) as seen at ``time``, in place, one by one:
    their positions ``pos``, times ``last``, streaks of frames seen in a row ``streak`` (0 for one not seen), and
    velocities ``vel``: one seen two frames in a row or more takes ``smoothing`` of its newest velocity into its
    smoothed one, one seen the frame before its newest, one found again after a gap its newest if the gap lasted no
    longer than ``max_coast_s``, else none (``Tracks.observe``; ``ModelLabeller``'s markers, with 0: none)."""
    for i in range(len(cur)):
        if not np.isfinite(cur[i, 0]):
            streak[i] = 0
            continue
        dt = time - last[i]
        for c in range(3):
            measured = (cur[i, c] - pos[i, c]) / dt
            # a track seen for the first or second time in a row has no velocity to smooth yet: it takes the measured
            # one, and none measured across a long gap, which says little about the motion now
            if streak[i] == 1:
                vel[i, c] = measured
            elif streak[i] == 0:
                vel[i, c] = measured if dt <= max_coast_s else 0.0
            else:
                vel[i, c] = vel[i, c] + smoothing * (measured - vel[i, c])
            pos[i, c] = cur[i, c]
        last[i] = time
        streak[i] += 1


@njit(cache=True)
def _remember(seen: np.ndarray, cur: np.ndarray, time: float, interval: float, anchors: np.ndarray,
              poses: np.ndarray, pose_count: np.ndarray, pose_time: np.ndarray,
              span: np.ndarray) -> None:  # pragma: no cover
    """``Tracks._remember`` in place, track by track."""
    width = anchors.shape[1]
    x = np.empty((width + 1, 3))
    for t in seen:
        if not time - pose_time[t] >= interval:
            continue
        x[0] = cur[t]
        visible = 0
        for j in range(width):
            a = anchors[t, j]
            if a >= 0 and np.isfinite(cur[a, 0]):
                x[j + 1] = cur[a]
                visible += 1
            else:
                x[j + 1] = np.nan
        if visible < 3:
            continue
        poses[t, pose_count[t] % poses.shape[1]] = x
        pose_count[t] += 1
        pose_time[t] = time
        for j in range(width):
            s = 0.0
            for c in range(3):
                d = x[j + 1, c] - x[0, c]
                s += d * d
            d = np.sqrt(s)
            if d < span[t, j, 0]:  # NaN (a neighbour not seen) leaves the range as it is
                span[t, j, 0] = d
            if d > span[t, j, 1]:
                span[t, j, 1] = d


class Tentatives:
    """Tentative tracks, in step with each other: last position, velocity and consecutive frames seen, all last seen
    at ``time`` (one missing a frame dies), and the trail of the points they collected: per frame, oldest first, the
    frame, the tentative tracks' positions in it and the row of each in the frame before (-1: started then), for at
    most ``frames`` frames (a tentative track held back by ``expected_markers`` keeps its last ``frames`` points)."""

    def __init__(self, frames: int) -> None:
        self.pos = np.empty((0, 3))
        self.vel = np.empty((0, 3))
        self.hits = np.empty(0, np.int64)
        self.time = -np.inf
        self.trail: deque[tuple[int, np.ndarray, np.ndarray]] = deque(maxlen=max(1, frames))

    def start(self, pos: np.ndarray, time: float, frame: int) -> None:
        """Replace the tentative tracks by new ones on the points ``pos`` ``(N, 3)`` seen at ``time`` in ``frame``."""
        self.pos = pos
        self.vel = np.zeros((len(pos), 3))
        self.hits = np.ones(len(pos), np.int64)
        self.time = time
        self.trail.clear()
        self.trail.append((frame, pos, np.full(len(pos), -1, np.intp)))

    def step(self, pos: np.ndarray, vel: np.ndarray, hits: np.ndarray, carried: np.ndarray, time: float,
             frame: int) -> None:
        """The tentative tracks seen at ``time`` in ``frame``: positions, velocities and frames seen, the first
        ``len(carried)`` carried on from the tentative tracks ``carried``, the others new."""
        back = np.full(len(pos), -1, np.intp)
        back[: len(carried)] = carried
        self.pos, self.vel, self.hits, self.time = pos, vel, hits, time
        self.trail.append((frame, pos, back))

    def points(self, u: int) -> tuple[np.ndarray, np.ndarray]:
        """The frames and positions ``(K, 3)`` of the points tentative track ``u`` collected, oldest first."""
        frames, pos = [], []
        for frame, at, back in reversed(self.trail):
            frames.append(frame)
            pos.append(at[u])
            u = int(back[u])
            if u < 0:
                break
        return np.array(frames[::-1]), np.array(pos[::-1])

    def keep(self, mask: np.ndarray) -> None:
        """Keep the tentative tracks selected by ``mask`` (T,) bool, drop the others."""
        self.pos, self.vel, self.hits = self.pos[mask], self.vel[mask], self.hits[mask]
        frame, _, back = self.trail.pop()
        self.trail.append((frame, self.pos, back[mask]))
