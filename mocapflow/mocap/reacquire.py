"""Finding a labeller's markers again when every one of them was lost at once (the labeller restarted).

After an occlusion a lost marker is found again from its neighbours that are still seen; after a restart none is seen,
so that cannot start. Each marker with its rigid partners (the markers whose distance to it varies by at most
``rigid_sd_mm``), where they were last seen together, is a small rigid layout; it is searched for in the new point
cloud by its pairwise distances, placed by a proper rotation (so a mirror image, the other side of the body, does not
fit), and the marker takes the point only when its whole layout fits one way far better than any other and no other
marker claims that point. Markers placed so pin their partners' layouts; a layout that still fits several ways (the
mirror-image segments of a body, a triangle of nearly equal sides) is decided by the distances to the nearby markers
placed so far (when they put every other way beyond 3 standard deviations), then by where each way puts those markers
(only while the best way puts them within the layout's own size: after a long restart they have moved otherwise, and
only for the way those distances, though unsure, rank first: a limb that swung through the restart can move its
neighbours to where the mirror image puts them). A marker placed so in two frames running is tracked again from the
second on, with the velocity of its step between them (a hand swinging through the restart moves farther in a frame
than the tracking gate); the others are looked for again in the next frames. Only this brings a track back: the
labeller relearns its other cues from scratch, so a marker that cannot be placed surely gets a new label rather than
another marker's.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np
from scipy.spatial.distance import cdist

from mocapflow.mocap.labelling import Labeller
from mocapflow.mocap.labelling.labeller import own_gates
from mocapflow.mocap.rigidfit import fit_one

TOLERANCE_MM = 4.0
"""Largest distance between a placed layout point and the cloud point it lands on."""
HIDDEN_MM = 10.0
"""What a layout point with no cloud point where it lands adds to a placement's misfit."""
AMBIGUITY = 3.0
"""A way to fit is sure when every other way scores this many times as much, plus a margin (``_sure``)."""
MARGIN_MM = 2.0
"""The margin of a layout's misfits: three markers fit their mirror image (the other side of the body) by a proper
rotation, within the noise of the positions saved and those seen now (0.15 against 1.5 mm RMS has been seen)."""
STEADIEST = 4
"""Placed markers that tell the ways a layout fits apart: those of the steadiest distance to it."""
IMPLAUSIBLE_SD = 3.0
"""Distances to those markers rule a way out only beyond this many standard deviations (RMS): across a joint they vary
by 20-60 mm, and the two ways of a triangle with two like sides differ by little more (on a simulated quadruped's
lower hind leg the wrong way scored 0.17, the right one 1.53)."""


Placement = tuple[float, np.ndarray, np.ndarray]  # misfit, rotation, translation


def _placements(layout: np.ndarray, cloud: np.ndarray, dist: np.ndarray,
                fixed: dict[int, int]) -> dict[int, Placement]:
    """For each point of ``cloud`` where the layout's first point lands when it and two more of its points fit (the
    others may be hidden) and its rows in ``fixed`` land on their points, the best such placement; its misfit is the
    RMS over the points that fit, plus ``HIDDEN_MM`` for each that does not."""
    d = cdist(layout, layout)
    found: dict[int, Placement] = {}
    for a, b in combinations(range(1, len(layout)), 2):
        base = [0, a, b]
        for i, j in np.argwhere(np.abs(dist - d[0, a]) < TOLERANCE_MM):
            ks = np.flatnonzero((np.abs(dist[i] - d[0, b]) < TOLERANCE_MM)
                                & (np.abs(dist[j] - d[a, b]) < TOLERANCE_MM))
            for k in ks[(ks != i) & (ks != j)]:
                fitted = fit_one(layout[base], cloud[[i, j, k]], np.ones(3))
                if fitted is None:  # three points in a line fix no rotation
                    continue
                rot, shift = fitted
                near = cdist(layout @ rot.T + shift, cloud)
                fit = near.min(axis=1)
                if (fit[base] < TOLERANCE_MM).all() and all(near[r, p] < TOLERANCE_MM for r, p in fixed.items()):
                    inside = fit < TOLERANCE_MM
                    misfit = float(np.sqrt(np.mean(fit[inside] ** 2))) + HIDDEN_MM * (~inside).sum()
                    if misfit < found.get(int(i), (np.inf,))[0]:
                        found[int(i)] = (misfit, rot, shift)
    return found


def _sure(scored: list[tuple[float, int]], margin: float = 1.0, beyond: float = 0.0) -> int | None:
    """The point of the best score when it is far better than every other: ``AMBIGUITY`` times, plus ``margin`` (in
    the scores' unit), and more than ``beyond``."""
    scored = sorted(scored)
    if scored and (len(scored) == 1 or scored[1][0] > max(AMBIGUITY * scored[0][0] + margin, beyond)):
        return scored[0][1]
    return None


class Reacquirer:
    """Finds a restarted labeller's tracks again, frame after frame, from their layouts as they were saved."""

    def __init__(self, labeller: Labeller) -> None:
        self.labeller = labeller
        tracks = labeller.tracks
        self.saved = tracks.pos.copy()
        n = tracks.pair_n
        self.sd = np.sqrt(tracks.pair_m2 / np.maximum(n - 1.0, 1.0))
        self.sd[n <= 1] = np.inf
        last = tracks.last
        self.layouts: dict[int, np.ndarray] = {}
        for t in range(len(labeller.labels)):
            mates = np.flatnonzero((self.sd[t] <= labeller.config.rigid_sd_mm) & (np.abs(last - last[t]) < 1e-6))
            members = np.concatenate([[t], mates[mates != t]])
            if len(members) >= 3 and np.isfinite(self.saved[t]).all():
                self.layouts[t] = members
        # Only these layouts bring a track back: the labeller's own cues (snapshots, partner distances) were learnt
        # before the gap and, with every marker lost at once, could hand a mirror-image marker to the wrong track.
        self.mean = tracks.pair_mean.copy()
        self.found: set[int] = set()  # tracks placed so far
        self._pending: dict[int, np.ndarray] = {}  # track -> where its layout put it surely in the previous frame
        self._previous = -np.inf  # time of that frame
        tracks.forget_cues()

    def __call__(self, points: np.ndarray, time: float) -> None:
        """Place the lost tracks on ``points`` captured at ``time`` where their layouts say surely. A track placed so in
        two frames running, by a step a marker can make, is followed from this frame on, with the velocity of that
        step (a hand swinging through a restart moves farther in a frame than the tracking gate), and joins
        ``found``."""
        lab = self.labeller.tracks
        lab.streak[time - lab.last > lab.config.max_coast_s] = 0  # tracks not seen since the restart are lost
        cloud = points[np.isfinite(points).all(axis=1)]
        if len(cloud) < 3:
            return
        dist = cdist(cloud, cloud)
        placed = _followed(self.labeller, cloud, time)  # track -> point
        followed = set(placed)
        while True:  # markers placed surely pin their partners' layouts, which then fit fewer ways
            claims: dict[int, list[int]] = {}
            for track, members in self.layouts.items():
                if track in placed:
                    continue
                fixed = {r: placed[m] for r, m in enumerate(members) if m in placed}
                found = {p: f for p, f in _placements(self.saved[members], cloud, dist, fixed).items()
                         if p not in placed.values()}
                point = _sure([(f[0], p) for p, f in found.items()], MARGIN_MM)
                if point is None and len(found) > 1:
                    distances = self._by_distances(track, members, found, cloud, placed)
                    point = _sure(distances, beyond=IMPLAUSIBLE_SD)
                    if point is None:
                        point = _sure(self._by_context(track, members, found, cloud, placed))
                        if distances and point != min(distances)[1]:  # the two cues disagree: neither decides
                            point = None
                if point is not None:
                    claims.setdefault(point, []).append(track)
            new = {tracks[0]: point for point, tracks in claims.items() if len(tracks) == 1}
            if not new:
                break
            placed.update(new)
        previous = self._previous
        before = self._pending if time - previous <= 1.5 / lab.rate else {}  # a frame went by unseen: start again
        self._pending, self._previous = {}, time
        for t, point in placed.items():
            if t in followed:
                continue
            at = before.get(t)
            if at is None or np.linalg.norm(cloud[point] - at) > lab.config.max_speed_mm_s * (time - previous):
                self._pending[t] = cloud[point]
                continue
            lab.pos[t], lab.vel[t] = at, (cloud[point] - at) / (time - previous)
            lab.last[t], lab.streak[t] = previous, 1  # as if followed from the previous frame
            self.found.add(t)

    def _steadiest(self, track: int, members: np.ndarray, placed: dict[int, int]) -> np.ndarray:
        others = np.array([t for t in placed if t not in members and np.isfinite(self.sd[track, t])], np.intp)
        return others[np.argsort(self.sd[track, others])[:STEADIEST]]

    def _by_distances(self, track: int, members: np.ndarray, found: dict[int, Placement], cloud: np.ndarray,
                      placed: dict[int, int]) -> list[tuple[float, int]]:
        """Ways a layout fits (the mirror-image segments of a body), scored by how well the distances from the
        marker's point to the steadiest placed markers outside the layout agree with the learnt ones (in standard
        deviations): they hold across a joint, whichever way it turned."""
        others = self._steadiest(track, members, placed)
        if len(others) == 0:
            return []
        mean = self.mean[track, others]
        sd = self.sd[track, others] + TOLERANCE_MM
        at = cloud[[placed[t] for t in others]]
        return [(float(np.sqrt(np.mean(((np.linalg.norm(at - cloud[p], axis=1) - mean) / sd) ** 2))), p)
                for p in found]

    def _by_context(self, track: int, members: np.ndarray, found: dict[int, Placement], cloud: np.ndarray,
                    placed: dict[int, int]) -> list[tuple[float, int]]:
        """Ways a layout fits (a triangle of nearly equal sides), scored by how far each puts the steadiest placed
        markers outside the layout from where they are (their positions before the restart, moved with the layout);
        none when even the best way puts them further off than the layout is wide."""
        others = self._steadiest(track, members, placed)
        if len(others) == 0:
            return []
        at = cloud[[placed[t] for t in others]]
        scored = [(float(np.median(np.linalg.norm(self.saved[others] @ rot.T + shift - at, axis=1))), p)
                  for p, (_, rot, shift) in found.items()]
        extent = cdist(self.saved[members], self.saved[members]).max()
        # those markers moved otherwise than the layout since it was saved (a limb swung through the restart): the
        # best way misplacing them by more than the layout's own size tells nothing of how the layout is turned
        return scored if min(scored)[0] <= extent else []


def _followed(labeller: Labeller, cloud: np.ndarray, time: float) -> dict[int, int]:
    """The points the tracks followed since the previous frame will take (nearest their prediction, in the gate)."""
    tracks = labeller.tracks
    live = np.flatnonzero(tracks.streak > 0)
    if len(live) == 0:
        return {}
    dt = time - tracks.last[live]
    pred = tracks.pos[live] + tracks.vel[live] * dt[:, None]
    d = cdist(pred, cloud)
    near = d.argmin(axis=1)
    ok = d[np.arange(len(live)), near] < own_gates(labeller.config.gate_mm, labeller.follow_mm, tracks.vel[live], dt)
    return {int(t): int(p) for t, p, good in zip(live, near, ok, strict=True) if good}
