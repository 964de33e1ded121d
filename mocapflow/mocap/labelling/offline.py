"""Offline labelling of a whole recording: streaming, then filling in what tentative tracks collected, cutting the
tracks streaming carried onto another marker, merging the tracks of one marker (the thesis's *Marker Set* merging),
dropping tracks too short to be markers and following the tracks back and on into the points left to none."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from scipy.spatial.distance import cdist

from mocapflow.mocap.clustering import noise_floor
from mocapflow.mocap.labelling.assignment import assign, norm, rigid_signature
from mocapflow.mocap.labelling.config import SD_FLOOR_MM, LabellerConfig
from mocapflow.mocap.labelling.labeller import Labeller
from mocapflow.mocap.labelling.placement import place_marker
from mocapflow.mocap.report import Progress, steps

BOUND_SLACK_MM = 20.0
"""How far a fitted snapshot may place a marker off its learnt distance to a neighbour, beyond three spreads."""
ARTICULATION = 5.0
"""Rigidity tells where the body moves: a track's distances to the others must spread (median SD) by this many times
``rigid_sd_mm`` for its rigid partners to say which marker it is. Over a stretch where the body only stands or walks
on, every marker is 'rigid' with dozens of others."""
LOOSE = 4.0
"""A pair of tracks whose rigid triangles match is merged unless its neighbours place one this many gates or more
from the other (a like triangle on the other side of the body)."""
WITNESSES = 3
"""A triangle with two like sides is told from its mirror image by this many markers across its joints at least,
each on the same side of the two triangles and none on opposite sides (``_triangle_score``). One such marker may lie
near the triangle's plane, and the joint's turn between the two sightings moves it across (the simulated human's
trunk: C7 and the sternum marker each 173 mm from the clavicle marker, in a plane 50 mm from the back pelvis marker
that alone told them apart, wrongly)."""
MUTUAL = 2.0
"""Two tracks whose neighbours place each other within this many gates, both ways (the median over frames), are one
marker when each fits the other best of all the tracks it could be, once nothing else merges. At most 2: beyond that,
``_set_score`` gives a pair it rules out by its distances only a lower bound."""
JUDGED_S = 30.0
"""A run after a gap is judged against at most this much of its track before the gap: as much of the neighbours'
motion as a whole capture of the stress benchmark shows, and a bound on the work, which would otherwise grow with the
square of a recording's length (a track of a long recording is joined across hundreds of gaps)."""
UNSIDED = 0.25
"""A pair of tracks whose triangles show no side (a hand that turns over, the forearm's markers nearly in its plane)
is merged by its triangle only where the neighbours leave it in doubt both ways and its three distances agree within
this share of their tolerance. A fragment of the same marker keeps them within its noise (0.00-0.03 of the tolerance,
58 such merges on the simulated rigs under stress); a look-alike elsewhere on the body does not (0.63-0.96: the
quadruped's two mirrored head markers, C7 and a marker at the back of the head, the two back pelvis markers)."""

SAME_MEANS = 0.6
"""Two tracks stand in one rigid triangle (``_triangle_score``) when their mean distances to the two partners, and the
partners' to each other, agree within this share of their tolerance (made for one frame's distance, not a mean over
many). Over the stress benchmark at seeds 1-6, the 230 triangle merges of fragments of one marker agreed within 0.53;
the two styloid markers of one wrist (hamner at seed 3), each as far from the forearm's upper marker and from the
elbow's within 9 mm, agreed within 0.87 and were merged."""


def merge_tracks(tracks: np.ndarray, rate: float, config: LabellerConfig | None = None,
                 progress: Progress | None = None) -> list[list[int]]:
    """Groups of tracks ``(F, T, 3)`` at ``rate`` Hz that are one physical marker: the thesis's merging of *Marker
    Sets*, offline.

    Online re-identification needs a lost track's neighbours to be known and seen when its marker comes back; a
    track lost before that, or whose neighbours were lost with it, comes back as a new track. Here every pair of
    tracks never seen together is compared as in Schoenauer (2007) section 3.3, on the thesis's local neighbourhood:
    snapshots of one track with its neighbours are fitted to those neighbours in the other track's frames, and the
    other track must lie within ``reid_gate_mm`` of the placed marker, or keep the distances to the first one's rigid
    partners; the median over frames decides (not the thesis's minimum, so that one coincidence cannot merge two
    markers).

    A track that takes up where another left off, within ``max_coast_s`` and on the other's constant-velocity course
    both ways, keeping its rigid distances (``_junctions``, ``_kept_distances``), is that marker too: a fast foot the
    stream lost for a few frames, which its neighbours place too loosely at that speed. A pair left in doubt (under
    ``LOOSE`` gates) is also compared by shape: two tracks that stand in one rigid triangle with two partners each
    (``_triangle_score``) are one marker, as when a foot hidden whole comes back as new tracks that its neighbours
    across the ankle place too loosely to tell. When no pair passes these, two tracks whose neighbours place each
    other within ``MUTUAL`` gates both ways, and which each fit the other best, are one marker (``_mutual``).

    Pairs are merged greedily, best first, never joining tracks seen in the same frame, and the comparison is
    repeated on the merged tracks until nothing changes: merging the fragments of one marker gives its neighbours'
    fragments the partners they lacked. ``progress`` is told of the pairs compared in each round.
    """
    cfg = config or LabellerConfig()
    groups = [[i] for i in range(tracks.shape[1])]
    rounds = 0
    while groups:
        rounds += 1
        state = _Round(_joined(tracks, groups), cfg)
        joins = _junctions(state, rate, cfg)
        scored = []
        pairs = np.argwhere(np.triu(state.overlap == 0, 1))
        both = np.full((len(groups), len(groups)), np.inf)  # per pair: the worse of its two set scores
        for i, j in steps(pairs.tolist(), len(pairs), f"merge, round {rounds} ({len(groups)} tracks)", progress):
            ways = (_set_score(state, i, j, cfg), _set_score(state, j, i, cfg))
            both[i, j] = both[j, i] = max(ways)
            score = min(ways)
            if score >= 1.0 and joins.get((i, j), np.inf) < 1.0:
                kept = max(_kept_distances(state, i, j, cfg), _kept_distances(state, j, i, cfg))
                score = min(score, max(joins[i, j], kept))
            if 1.0 <= score < LOOSE:
                score = min(score, _triangle_score(state, i, j, cfg, both[i, j] < LOOSE))
            if score < 1.0:
                scored.append((score, i, j))
        if not scored:
            scored = _mutual(both, state.seen.sum(axis=0) >= cfg.min_track_s * rate)
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


def _joined(tracks: np.ndarray, groups: list[list[int]]) -> np.ndarray:
    """Each group of columns of ``tracks`` ``(F, T, 3)`` as one track, ``(F, G, 3)``: the tracks of a group (from
    ``merge_tracks``) never share a frame."""
    if not groups:
        return np.full((len(tracks), 0, 3), np.nan)
    return np.stack([np.fmax.reduce(tracks[:, group], axis=1) for group in groups], axis=1)


def _mutual(both: np.ndarray, long: np.ndarray) -> list[tuple[float, int, int]]:
    """Pairs of tracks (score, i, j), one of them ``long`` (seen for ``min_track_s`` or more), whose set scores both
    ways (``both``, the worse of the two) are below ``MUTUAL`` and each of which fits the other better than any other
    track it was compared with: a fragment of a marker that its neighbours place too loosely for the first rules (a
    marker across a joint from them, some of them hidden), where every other track is placed farther off. Two short
    fragments are not joined so: their neighbours are learnt over too short a time."""
    best = both.argmin(axis=1)
    return [(float(both[i, j]), int(i), int(j)) for i, j in enumerate(best.tolist())
            if i < j and best[j] == i and both[i, j] < MUTUAL and (long[i] or long[j])]


class _Round:
    """One round of ``merge_tracks``: the merged tracks so far and what every comparison of a pair reuses, each worked
    out once: which frames each track is seen in (and an even sample of them), in how many frames each pair is seen
    together, and each track's distance statistics."""

    def __init__(self, tracks: np.ndarray, cfg: LabellerConfig) -> None:
        self.tracks = tracks
        self.seen = np.isfinite(tracks[..., 0])
        as_float = self.seen.astype(np.float64)  # frame counts are exact in floats, whose product BLAS does fast
        self.overlap = np.rint(as_float.T @ as_float).astype(np.int64)
        self.frames = [np.flatnonzero(column) for column in self.seen.T]
        self.sampled = [_evenly(f, cfg.poses) for f in self.frames]
        self._cfg = cfg
        self._spreads: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._neighbours: dict[int, np.ndarray] = {}

    def refresh(self, columns: list[int]) -> None:
        """Take in the ``columns`` of ``tracks`` changed in place: what is seen, the overlaps and frames; the
        distance statistics are worked out again as asked."""
        for c in columns:
            self.seen[:, c] = np.isfinite(self.tracks[:, c, 0])
            self.frames[c] = np.flatnonzero(self.seen[:, c])
            self.sampled[c] = _evenly(self.frames[c], self._cfg.poses)
        rows = np.array([self.seen[self.frames[c]].sum(axis=0) for c in columns], np.int64).reshape(len(columns), -1)
        self.overlap[columns] = rows
        self.overlap[:, columns] = rows.T
        self._spreads.clear()
        self._neighbours.clear()

    def same_side(self, first: tuple[int, int, int], second: tuple[int, int, int]) -> int:
        """Whether two triangles of tracks (``a``, ``b``, ``c``) are alike or mirror images, seen from their first
        corner: how many tracks near both (both first corners' steadiest neighbours that are not rigid with them: the
        markers across the joints) lie on one side of each in 90 % of the frames they are seen with it, -1 when one
        lies on opposite sides so, 0 when none tells (no such neighbour in common, as for the two legs' like clusters;
        a neighbour in the triangle's plane; a hand turning over)."""
        near = np.intersect1d(self._steadiest(first), self._steadiest(second))
        near = near[~np.isin(near, first + second)]
        sides = np.array([self._side(first, near), self._side(second, near)])  # (2, N): +1, -1, 0
        votes = sides[0] * sides[1]
        return -1 if (votes < 0).any() else int((votes > 0).sum())

    def _steadiest(self, triangle: tuple[int, int, int]) -> np.ndarray:
        """The first corner's steadiest neighbours that are not rigid with it (twice as many as place a marker, so
        that two tracks of one marker have some in common)."""
        _, sd = self.spread(triangle[0])
        steady = np.where(np.isfinite(sd) & (sd > self._cfg.rigid_sd_mm), sd, np.inf)
        steady[list(triangle)] = np.inf
        nb = np.argsort(steady)[: 2 * self._cfg.neighbours]
        return nb[np.isfinite(steady[nb])]

    def _side(self, triangle: tuple[int, int, int], near: np.ndarray) -> np.ndarray:
        """On which side of the triangle each of the ``near`` tracks lies: +1 or -1 where it holds in 90 % of the
        frames (at least ``offline_confirm_frames``) they are seen together, else 0."""
        a, b, c = triangle
        frames = self.seen[:, a] & self.seen[:, b] & self.seen[:, c]
        x = self.tracks[frames]
        normal = np.cross(x[:, b] - x[:, a], x[:, c] - x[:, a])
        out = np.zeros(len(near), np.int64)
        for k, n in enumerate(near.tolist()):
            shown = self.seen[frames, n]
            if shown.sum() < self._cfg.offline_confirm_frames:
                continue
            share = (np.einsum("fi,fi->f", normal[shown], x[shown, n] - x[shown, a]) > 0).mean()
            out[k] = 1 if share >= 0.9 else -1 if share <= 0.1 else 0
        return out

    def neighbours(self, i: int) -> np.ndarray:
        """The tracks that may serve as track ``i``'s neighbours (distance spread at most ``neighbour_sd_mm``),
        steadiest first (spread plus 2 % of the distance, so that near ones win a tie)."""
        if i not in self._neighbours:
            mean, sd = self.spread(i)
            score = np.where(sd <= self._cfg.neighbour_sd_mm, sd + 0.02 * mean, np.inf)  # NaN: too few frames shared
            score[i] = np.inf
            order = np.argsort(score, kind="stable")
            self._neighbours[i] = order[np.isfinite(score[order])]
        return self._neighbours[i]

    def spread(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """``_distance_spread`` of track ``i``."""
        if i not in self._spreads:
            self._spreads[i] = _distance_spread(self.tracks, self.seen, i, self._cfg.offline_confirm_frames)
        return self._spreads[i]


def _distance_spread(tracks: np.ndarray, seen: np.ndarray, i: int, least: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation of track ``i``'s distance to every track over the frames they share; NaN where
    they share fewer than ``least`` frames (or than ``i`` has)."""
    d = norm(tracks[seen[:, i], i, None] - tracks[seen[:, i]])
    count = np.isfinite(d).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.nansum(d, axis=0) / count
        sd = np.sqrt(np.nansum((d - mean) ** 2, axis=0) / count)
    few = count < min(len(d), least)
    mean[few] = sd[few] = np.nan
    return mean, sd


def _set_score(state: _Round, i: int, j: int, cfg: LabellerConfig) -> float:
    """How well track ``j`` fits marker ``i`` in ``j``'s frames, below 1 when it is the same marker.

    The median over (at most ``poses``) frames of the smaller of: the distance to where ``i``'s neighbours place it,
    in units of ``reid_gate_mm``; the worst error of its distances to ``i``'s rigid partners (two or more seen), in
    units of their tolerance (``rigid_signature``). Where a bound on that distance from ``j``'s distances to the
    neighbours alone already puts the median at 2 or more, the bound is returned and nothing is fitted.
    """
    tracks, seen = state.tracks, state.seen
    fi, b = state.frames[i], state.sampled[j]
    mean, sd = state.spread(i)
    signature = _signature(state, i, j, cfg)
    nb = state.neighbours(i)
    nb = nb[(nb != j) & (state.overlap[j, nb] >= 3)][: cfg.neighbours]
    placed = np.full(len(b), np.inf)
    a = _evenly(fi[seen[fi][:, nb].sum(axis=1) >= 3], cfg.poses)
    if len(nb) >= 3 and len(a):
        # First a bound that needs no fit: in a frame where a snapshot shares three neighbours with it (so the marker
        # can be placed), the placed marker keeps nearly its learnt distances to three or more of them, so it lies at
        # least as far from track j as j's third best distance is from those. Most pairs are told apart by that alone.
        off = np.abs(norm(tracks[b, j, None] - tracks[b][:, nb]) - mean[nb]) - 3.0 * sd[nb] - BOUND_SLACK_MM
        third = np.sort(np.where(np.isfinite(off), off, np.inf), axis=1)[:, 2]
        shared = seen[b][:, nb].astype(np.int64) @ seen[a][:, nb].T.astype(np.int64)
        bound = np.where(shared.max(axis=1) >= 3, np.maximum(third, 0.0) / cfg.reid_gate_mm, np.inf)
        lower = np.minimum(bound, signature)
        lower = lower[np.isfinite(lower)]
        if len(lower) and _median(lower) >= 2.0:
            return _median(lower)
        poses = np.concatenate([tracks[a, i, None], tracks[a][:, nb]], axis=1)
        trust = np.broadcast_to(1.0 / (sd[nb] ** 2 + SD_FLOOR_MM**2), (len(b), len(nb)))
        place, _, _ = place_marker(np.broadcast_to(poses, (len(b), *poses.shape)), tracks[b][:, nb], trust,
                             cfg.instant_fit_mm)
        err = norm(place - tracks[b, j]) / cfg.reid_gate_mm
        placed = np.where(np.isfinite(err), err, np.inf)
    best = np.minimum(placed, signature)
    best = best[np.isfinite(best)]
    return _median(best) if len(best) else np.inf


def split_doubtful_joins(tracks: np.ndarray, rate: float,
                         config: LabellerConfig | None = None) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """Tracks ``(F, T, 3)`` at ``rate`` Hz cut where a run after a gap is surely another marker than the track before
    it, and the joins left in doubt: (column of the tracks returned, frame the run starts).

    Streaming re-identifies a lost track on a point that fits its hypotheses then; now and then the point is another
    marker's (a segment mate, a marker of the other side), and the track goes on as that marker. Offline, each run
    after a gap is compared with the track's frames before it (since its last cut, the last ``JUDGED_S`` at most) as
    fragments are (``_set_score``, both ways, the other tracks whole): where the neighbours of either place the other
    ``LOOSE`` gates off or more, both ways, the run starts a new track, for merging to join to its own marker. Where
    neither way places the other within the gate (a way with nothing to place confirms nothing), the join stands but
    is in doubt: ``label_sequence`` looks at it again once the fragments are merged (``_second_look``).
    """
    cfg = config or LabellerConfig()
    seen = np.isfinite(tracks[..., 0])
    starts, ends = run_starts(seen), run_starts(seen[::-1])[::-1]
    joined = np.flatnonzero(starts.sum(axis=0) >= 2)
    if not len(joined):
        return tracks, []
    count = tracks.shape[1]
    work = np.concatenate([tracks, np.full((len(tracks), 1, 3), np.nan)], axis=1)  # the last column: a run
    state = _Round(work, cfg)
    cuts: dict[int, list[int]] = {}
    doubts: list[tuple[int, int, int]] = []  # (track, cuts before it, frame)
    for t in joined.tolist():
        first, last = np.flatnonzero(starts[:, t]), np.flatnonzero(ends[:, t]) + 1
        begin = first[0]
        for run in range(1, len(first)):
            work[:, t] = np.nan
            since = max(begin, first[run] - round(JUDGED_S * rate))
            work[since:first[run], t] = tracks[since:first[run], t]
            work[:, count] = np.nan
            work[first[run]:last[run], count] = tracks[first[run]:last[run], t]
            state.refresh([t, count])
            scores = (_set_score(state, t, count, cfg), _set_score(state, count, t, cfg))
            if LOOSE <= min(scores) and max(scores) < np.inf:
                cuts.setdefault(t, []).append(int(first[run]))
                begin = first[run]
            elif min(scores) >= 1.0:
                doubts.append((t, len(cuts.get(t, [])), int(first[run])))
        work[:, t] = tracks[:, t]  # the other joins are judged against the tracks as streamed
    work[:, count] = np.nan
    out = work[:, :count]
    pieces: list[np.ndarray] = []
    column: dict[tuple[int, int], int] = {}  # (track, cuts before it) -> the column of that piece
    for t, at in cuts.items():
        column.update({(t, k + 1): count + len(pieces) + k for k in range(len(at))})
        out[at[0]:, t] = np.nan
        pieces += _cut(tracks[:, t], [*at, len(tracks)])
    doubtful = [(column.get((t, k), t), frame) for t, k, frame in doubts]
    return np.concatenate([out, *[p[:, None] for p in pieces]], axis=1), doubtful


def _cut(track: np.ndarray, bounds: list[int]) -> list[np.ndarray]:
    """``track`` ``(F, 3)`` cut at ``bounds`` (frames, increasing): one track per span between two bounds, NaN
    elsewhere."""
    pieces = []
    for begin, end in zip(bounds[:-1], bounds[1:], strict=True):
        piece = np.full_like(track, np.nan)
        piece[begin:end] = track[begin:end]
        pieces.append(piece)
    return pieces


def _second_look(merged: np.ndarray, doubtful: list[tuple[int, int]], rate: float, cfg: LabellerConfig,
                 progress: Progress | None) -> np.ndarray:
    """Merged tracks ``(F, T, 3)`` looked at again at the joins left in doubt (``doubtful``: (column, frame), from
    ``split_doubtful_joins``).

    A join the neighbours confirm neither way may be right (a marker whose neighbours were hidden with it) or another
    marker's run (a segment mate that came back first). Its fragments merged, each merged track is cut at its joins
    in doubt, and the pieces are merged again, with the whole recording's evidence: a piece that is another marker
    finds that marker's track. Two pieces of one track whose merged tracks never share a frame are then one marker
    still, and joined again (the nearest piece before first), so that a join merging cannot better is never lost,
    and no more tracks are left than before.
    """
    if not doubtful:
        return merged
    at: dict[int, set[int]] = {}
    for k, frame in doubtful:
        at.setdefault(k, set()).add(frame)
    pieces: list[np.ndarray] = []
    chains: list[list[int]] = []  # per merged track, the columns of its pieces in order
    for k in range(merged.shape[1]):
        held = [piece for piece in _cut(merged[:, k], [0, *sorted(at.get(k, ())), len(merged)])
                if np.isfinite(piece[:, 0]).any()]
        chains.append(list(range(len(pieces), len(pieces) + len(held))))
        pieces += held
    cut = np.stack(pieces, axis=1)
    seen = np.isfinite(cut[..., 0])
    again = merge_tracks(cut, rate, cfg, progress)
    where = {c: k for k, group in enumerate(again) for c in group}
    for chain in chains:
        for k, b in enumerate(chain):
            for a in chain[k - 1::-1] if k else ():  # the pieces before it, nearest first
                ga, gb = where[a], where[b]
                if ga != gb and not (seen[:, again[ga]].any(axis=1) & seen[:, again[gb]].any(axis=1)).any():
                    where.update({c: ga for c in again[gb]})
                    again[ga], again[gb] = again[ga] + again[gb], []
                    break
    return _joined(cut, [group for group in again if group])


def extend_tracks(tracks: np.ndarray, clouds: list[np.ndarray], config: LabellerConfig | None = None) -> np.ndarray:
    """Tracks ``(F, T, 3)`` followed from each end, back in time and then on, into the points of ``clouds`` (per frame
    ``(M, 3)``, NaN rows ignored) that no track holds.

    Streaming starts a track only once a point has lived ``confirm_frames`` and been told from its neighbours' points,
    and a point seen once has no velocity: where markers move fast (a sprinter's foot, 140 mm a frame at 125 Hz, at the
    capture's start or as it leaves the ground), a foot's markers are taken for one another's until it slows, and
    their points are left to no track meanwhile. Offline, a track's frames on the far side give its velocity: each
    track is followed frame by frame from its ends as streaming follows it (constant velocity from its two nearest
    frames, within ``gate_mm`` at any rate, one optimal assignment per frame), back in time first, then on. Below
    100 Hz streaming widens a moving track's gate (``LabellerConfig.follow_gate``); here that took other markers'
    points and ghosts at the tracks' ends under heavy damage. A chain of points so added that meets the track's other
    side across a gap, or another chain, stays only if one side can be followed into the other (one way is enough:
    where a foot leaves the ground, the step on is the one streaming failed); else the end it grew from was another
    marker's point, and it is taken out again.
    """
    cfg = config or LabellerConfig()
    out = tracks.copy()
    gate = cfg.gate_mm
    chain = np.zeros(out.shape[:2], np.intp)  # per point: 0 as the tracks were, else the chain that added it
    chains = 0
    for way in (-1, 1):
        for f in range(len(out) - 2, -1, -1) if way < 0 else range(1, len(out)):
            last = f - way  # the frame each track's end was seen in
            ends = np.flatnonzero(np.isnan(out[f, :, 0]) & np.isfinite(out[last, :, 0]))
            cloud = np.asarray(clouds[f], dtype=float).reshape(-1, 3)
            free = np.isfinite(cloud).all(axis=1)
            if not len(ends) or not free.any():
                continue
            held = source_rows(out[f], cloud)
            free[held[held >= 0]] = False
            rows = np.flatnonzero(free)
            before = out[last - way, ends] if 0 <= last - way < len(out) else np.full((len(ends), 3), np.nan)
            ti, pi = assign(_course(out[last, ends], before), gate, cloud[rows])
            grown = ends[ti]
            out[f, grown] = cloud[rows[pi]]
            ids = chain[last, grown]
            fresh = ids == 0
            ids[fresh] = chains + 1 + np.arange(int(fresh.sum()))
            chains += int(fresh.sum())
            chain[f, grown] = ids
    seen = np.isfinite(out[..., 0])
    # where a chain meets what it did not grow from: frame ``at`` and the next, of track ``k``
    at, k = np.nonzero(seen[:-1] & seen[1:] & (chain[:-1] != chain[1:]))
    if len(at):
        early = np.where((at > 0)[:, None], out[np.maximum(at - 1, 0), k], np.nan)
        late = np.where((at + 2 < len(out))[:, None], out[np.minimum(at + 2, len(out) - 1), k], np.nan)
        bad = (norm(out[at + 1, k] - _course(out[at, k], early)) > gate) & (
            norm(out[at, k] - _course(out[at + 1, k], late)) > gate)
        wrong = np.setdiff1d(np.concatenate([chain[at[bad], k[bad]], chain[at[bad] + 1, k[bad]]]), 0)
        out[np.isin(chain, wrong)] = np.nan
    return out


def _course(here: np.ndarray, before: np.ndarray) -> np.ndarray:
    """Where markers at ``here`` ``(N, 3)`` are one frame on at constant velocity, from ``before`` (one frame back; NaN
    rows: at rest)."""
    return here + np.nan_to_num(here - before)


def run_starts(seen: np.ndarray) -> np.ndarray:
    """``(F, T)``: where each track's runs of frames seen in a row (``seen`` ``(F, T)``) begin."""
    return seen & ~np.vstack([np.zeros((1, seen.shape[1]), bool), seen[:-1]])


def _junctions(state: _Round, rate: float, cfg: LabellerConfig) -> dict[tuple[int, int], float]:
    """Pairs of tracks (``i < j``) one of which takes up where the other left off within ``max_coast_s``: the worst,
    over their junctions, of how far each end's constant-velocity step across the gap lands from the other end,
    forward and backward, in units of the coast's gate (``LabellerConfig.coast_gate``). Below 1 a fast marker the
    streaming follow lost for a frame or two (a foot at 10 m/s) is the same marker; both must fit, and every junction
    between the two."""
    seen, tracks = state.seen, state.tracks
    longest = max(1, round(cfg.max_coast_s * rate))
    worst: dict[tuple[int, int], float] = {}
    starts = np.argwhere(seen[1:] & ~seen[:-1]) + [1, 0]  # (frame, track) where a run begins
    for s, y in starts.tolist():
        if s + 1 >= len(seen) or not seen[s + 1, y]:
            continue
        first = max(0, s - longest)
        before = seen[first:s]  # who was seen in the frames just before
        for x in np.flatnonzero(before.any(axis=0) & ~seen[s]).tolist():
            if x == y or state.overlap[x, y]:
                continue
            a = first + int(np.flatnonzero(before[:, x])[-1])  # x's last frame before y's run
            gap = s - a
            if a < 1 or not seen[a - 1, x]:
                continue
            forward = tracks[a, x] + (tracks[a, x] - tracks[a - 1, x]) * gap
            backward = tracks[s, y] - (tracks[s + 1, y] - tracks[s, y]) * gap
            gate = cfg.coast_gate(gap / rate, rate)
            error = max(float(np.linalg.norm(forward - tracks[s, y])), float(np.linalg.norm(backward - tracks[a, x])))
            key = (min(x, y), max(x, y))
            worst[key] = max(worst.get(key, 0.0), error / gate)
    return worst


def _rigid_partners(sd: np.ndarray, cfg: LabellerConfig, *others: int) -> np.ndarray:
    """The tracks rigid with one whose distance spreads to every track are ``sd``, ``others`` left out."""
    rigid = sd <= cfg.rigid_sd_mm  # NaN (too few frames shared) is no partner
    rigid[list(others)] = False
    return np.flatnonzero(rigid)


def _signature(state: _Round, i: int, j: int, cfg: LabellerConfig) -> np.ndarray:
    """In each of track ``j``'s sampled frames, the worst error of its distances to track ``i``'s rigid partners, in
    units of their tolerance (``rigid_signature``); inf where fewer than two of them are seen."""
    mean, sd = state.spread(i)
    partners = _rigid_partners(sd, cfg, i, j)
    b = state.sampled[j]
    broken, count, _ = rigid_signature(state.tracks[b, j], state.tracks[b][:, partners], mean[None, partners],
                                       sd[None, partners], cfg.rigid_tolerance_mm)
    return np.where(count[0] >= 2, broken[0], np.inf)


def _kept_distances(state: _Round, i: int, j: int, cfg: LabellerConfig) -> float:
    """How well track ``j`` keeps track ``i``'s distances to its rigid partners: the median of ``_signature`` over
    the frames where it tells, 0 where none does."""
    told = _signature(state, i, j, cfg)
    told = told[np.isfinite(told)]
    return _median(told) if len(told) else 0.0


def _triangle_score(state: _Round, i: int, j: int, cfg: LabellerConfig, in_doubt: bool) -> float:
    """How well two tracks never seen together stand in one rigid triangle with two partners each: below 1 when
    ``i`` with two of its rigid partners and ``j`` with two of its own keep the same three distances (within
    ``SAME_MEANS`` of ``rigid_tolerance_mm`` plus three spreads), each partner of ``i`` being the matching partner of
    ``j`` or a track never seen with it, and both tracks seen while the body moved (``ARTICULATION``). A body part
    whose markers all came back as new tracks (a foot hidden whole) is known again by its shape, where its neighbours
    across the joints place a marker too loosely to say.

    A triangle whose three sides differ by more than the tolerance of a match cannot be matched the wrong way round. One
    with two like sides (a head's two side markers, each as far from the third) fits its mirror image, which is the same
    triangle with its two partners swapped: it counts only where ``WITNESSES`` markers across its joints show plainly
    that they lie on the same side of both (a swap turns the triangle over). One with three like sides also fits itself
    turned round, its markers relabelled in turn, which keeps the side: it never counts. And the markers across their
    joints must lie on the same side of both triangles (``_Round.same_side``): the other leg's cluster may have the same
    shape, mirrored. A pair with no partner in common must show that side plainly, unless ``in_doubt`` (the neighbours
    leave it in doubt both ways) and its three distances agree within ``UNSIDED`` of their tolerance; one with a partner
    in common is held by that partner where the side changes with the pose (a hand turning over). And a pair whose
    triangles some match shows mirrored (a marker across the joints on opposite sides) counts only by a match that
    ``WITNESSES`` markers show on the same side: with fragments for partners, another match of the same two triangles
    may show no side at all (a symmetric body's two thighs)."""
    mean_i, sd_i = state.spread(i)
    mean_j, sd_j = state.spread(j)
    if not min(np.nanmedian(sd_i), np.nanmedian(sd_j)) >= ARTICULATION * cfg.rigid_sd_mm:
        return np.inf
    rigid_i = _rigid_partners(sd_i, cfg, i, j).tolist()
    rigid_j = _rigid_partners(sd_j, cfg, i, j).tolist()
    matched = []
    for p in rigid_i:
        for q in rigid_j:
            tol = cfg.rigid_tolerance_mm + 3.0 * max(sd_i[p], sd_j[q])
            if (p == q or state.overlap[p, q] == 0) and abs(mean_i[p] - mean_j[q]) <= tol:
                matched.append((p, q, abs(mean_i[p] - mean_j[q]) / tol, tol))
    kept: list[tuple[float, int]] = []  # (error, witnesses) of each way the two triangles match
    mirrored = False
    for a, (p1, q1, e1, t1) in enumerate(matched):
        for p2, q2, e2, t2 in matched[a + 1:]:
            if p1 == p2 or q1 == q2:
                continue
            mean_p, sd_p = state.spread(p1)
            mean_q, sd_q = state.spread(q1)
            t3 = cfg.rigid_tolerance_mm + 3.0 * max(sd_p[p2], sd_q[q2])
            e3 = abs(mean_p[p2] - mean_q[q2]) / t3
            if not e3 <= 1.0:
                continue
            sides = np.sort([mean_i[p1], mean_i[p2], mean_p[p2]])
            like = max(t1, t2, t3)
            side = state.same_side((i, p1, p2), (j, q1, q2))
            if np.diff(sides).min() <= like and (side < WITNESSES or sides[2] - sides[0] <= like):
                continue  # like sides: the triangle fits itself another way round (see above)
            error = max(e1, e2, e3)
            if error > SAME_MEANS:
                continue
            mirrored |= side < 0
            if side < 0 or (side == 0 and p1 != q1 and p2 != q2 and not (in_doubt and error <= UNSIDED)):
                continue
            kept.append((error, side))
    return min((error for error, witnesses in kept if witnesses >= WITNESSES or not mirrored), default=np.inf)


def _explained(tracks: np.ndarray, seen: np.ndarray, k: int, rigid_sd: float, least: int) -> bool:
    """Whether track ``k`` keeps its distances to other tracks within ``rigid_sd`` (mm, SD) while it moves (its
    positions spread by more than ``rigid_sd`` mm, RMS, over the frames they share): a real marker on a rigid body,
    however briefly seen, not a ghost. A track seen in one unbroken run is one object throughout, so one partner seen
    with it for ``least`` frames vouches for it; a track merged from fragments across gaps needs two, seen in every
    one of its frames, since fragments of ghosts merge too, or one for each of its runs, every run vouched for on its
    own as an unbroken track is (a marker whose segment shows only two markers, seen twice). Distances that hold while
    nothing moves prove nothing: a reflection that stands still keeps its distances to other still reflections, and
    over a few frames to any slow marker. A track seen in fewer than ``least`` frames in all (a piece that splitting cut
    off, two ghosts in consecutive frames taken for one point) has no partner seen with it for that long, and no
    partner vouches for it."""
    frames = np.flatnonzero(seen[:, k])
    if len(frames) < least:
        return False
    runs = np.split(frames, np.flatnonzero(np.diff(frames) > 1) + 1)
    if len(runs) == 1:
        return _partners(tracks, seen, k, rigid_sd, least) >= 1
    if _partners(tracks, seen, k, rigid_sd, len(frames)) >= 2:
        return True
    alone = seen.copy()
    for run in runs:
        alone[:, k] = False
        alone[run, k] = True
        if len(run) < least or _partners(tracks, alone, k, rigid_sd, least) < 1:
            return False
    return True


def _partners(tracks: np.ndarray, seen: np.ndarray, k: int, rigid_sd: float, least: int) -> int:
    """How many tracks keep their distances to track ``k`` within ``rigid_sd`` (mm, SD) over at least ``least`` of
    its frames (all of them, if it has fewer), while ``k`` moves by more than that over the frames they share."""
    frames = np.flatnonzero(seen[:, k])
    _, sd = _distance_spread(tracks, seen, k, least)
    sd[k] = np.nan
    shared = seen[frames].astype(float)  # (n, T): the frames k shares with each track
    count = shared.sum(axis=0)
    own = tracks[frames, k]
    with np.errstate(invalid="ignore", divide="ignore"):
        centre = shared.T @ own / count[:, None]  # (T, 3): k's mean position over the frames shared with each
        motion = np.sqrt(np.maximum(shared.T @ (own**2).sum(axis=1) / count - (centre**2).sum(axis=1), 0.0))
    return int(((sd <= rigid_sd) & (motion > rigid_sd)).sum())


def _rigid_sd(tracks: np.ndarray, seen: np.ndarray, markers: np.ndarray, cfg: LabellerConfig) -> float:
    """How much the distance between two markers of one rigid body varies in this recording (SD, mm): three times
    its noise floor (``clustering.noise_floor``, read on the tracks ``markers`` long enough to be markers), at least
    ``rigid_sd_mm``. Skin on a sprinter's legs moves markers several millimetres where a rigid cluster holds one."""
    spread = np.full((len(markers), len(markers)), np.nan)
    for row, k in enumerate(markers):
        spread[row] = _distance_spread(tracks, seen, k, cfg.offline_confirm_frames)[1][markers]
    return max(cfg.rigid_sd_mm, 3.0 * noise_floor(spread)) if len(markers) > 1 else cfg.rigid_sd_mm


def _median(values: np.ndarray) -> float:
    """The median of a short array of numbers, as ``np.median`` gives it at a fraction of its cost."""
    ordered = np.sort(values)
    return float((ordered[(len(ordered) - 1) // 2] + ordered[len(ordered) // 2]) / 2)


def _evenly(frames: np.ndarray, count: int) -> np.ndarray:
    """At most ``count`` of ``frames``, evenly spread."""
    if len(frames) <= count:
        return frames
    return frames[np.linspace(0, len(frames) - 1, count).round().astype(int)]


def label_sequence(frames: Iterable[np.ndarray], rate: float, config: LabellerConfig | None = None,
                   progress: Progress | None = None) -> tuple[np.ndarray, list[str]]:
    """Label a whole recording of point clouds: ``(F, T, 3)`` trajectories of the ``T`` markers found, and labels.

    Knowing the whole recording allows more than streaming: points a track collected while still tentative are filled
    in, tracks carried across a gap onto another marker are cut there (:func:`split_doubtful_joins`), tracks of one
    marker are merged (:func:`merge_tracks`), tracks seen for less than ``min_track_s`` in all are dropped unless rigid
    partners explain them (``_markers``), the joins left in doubt are looked at again on the tracks kept
    (``_second_look``; a piece it leaves too short is dropped so too), and the tracks kept are followed from their ends
    into the points left to none (:func:`extend_tracks`). Markers are labelled ``M001``... in order of first appearance.
    ``progress`` is told how the merging goes (its cost grows with the square of the number of tracks).
    """
    cfg = config or LabellerConfig()
    labeller = Labeller(cfg.model_copy(update={"confirm_frames": cfg.offline_confirm_frames}), rate)
    rows: list[np.ndarray] = []
    clouds: list[np.ndarray] = []
    late: list[tuple[int, np.ndarray, np.ndarray]] = []
    for i, points in enumerate(frames):
        clouds.append(np.asarray(points, dtype=float).reshape(-1, 3))
        result = labeller.update(clouds[-1], i / rate)
        rows.append(result.positions)
        late += result.history
    tracks = np.full((len(rows), len(labeller.labels), 3), np.nan)
    for i, row in enumerate(rows):
        tracks[i, : len(row)] = row
    for track, idx, pos in late:
        tracks[idx, track] = pos
    tracks, doubtful = split_doubtful_joins(tracks, rate, cfg)
    groups = merge_tracks(tracks, rate, cfg, progress)
    joined = _joined(tracks, groups)
    kept = _markers(joined, rate, cfg)
    # the joins in doubt on the tracks kept, by column of those: a track dropped takes up no piece of another marker
    column = {k: c for c, k in enumerate(kept)}
    where = {t: column[k] for k, group in enumerate(groups) if k in column for t in group}
    joined = _second_look(joined[:, kept], [(where[t], frame) for t, frame in doubtful if t in where], rate, cfg,
                          progress)
    out = joined[:, _markers(joined, rate, cfg)]
    out = out[:, np.argsort([np.flatnonzero(np.isfinite(out[:, k, 0]))[0] for k in range(out.shape[1])],
                           kind="stable")]
    return extend_tracks(out, clouds, cfg), [f"M{k + 1:03d}" for k in range(out.shape[1])]


def _markers(tracks: np.ndarray, rate: float, cfg: LabellerConfig) -> list[int]:
    """The columns of ``tracks`` ``(F, T, 3)`` that are markers: seen for ``min_track_s`` in all, or explained by
    rigid partners (``_explained``, at this recording's rigidity: ``_rigid_sd``)."""
    seen = np.isfinite(tracks[..., 0])
    long = seen.sum(axis=0) >= cfg.min_track_s * rate
    rigid_sd = _rigid_sd(tracks, seen, np.flatnonzero(long), cfg) if not long.all() else cfg.rigid_sd_mm
    return [k for k in range(tracks.shape[1])
            if long[k] or _explained(tracks, seen, k, rigid_sd, cfg.offline_confirm_frames)]


def source_rows(positions: np.ndarray, cloud: np.ndarray) -> np.ndarray:
    """The row of ``cloud`` ``(M, 3)`` each of ``positions`` ``(T, 3)`` was copied from, as a labelling holds its
    points: -1 for a NaN position, or one that is none of the cloud's points (within 1e-6 mm)."""
    rows = np.full(len(positions), -1, np.intp)
    seen = np.flatnonzero(np.isfinite(positions).all(axis=1))
    if len(seen) and len(cloud):
        d = cdist(positions[seen], np.nan_to_num(np.asarray(cloud, dtype=float), nan=np.inf))
        near = d.argmin(axis=1)
        hit = d[np.arange(len(seen)), near] <= 1e-6
        rows[seen[hit]] = near[hit]
    return rows
