"""Naming trajectories from a skeleton where no single frame can: evidence gathered over their whole length, or
live, over their runs so far (:class:`RunningEvidence`).

A segment is posed in a frame only when three of its references (its markers, the centres of its joints to posed
neighbours) are seen together. A leg whose thigh and shank have two markers each, half of them hidden at any time,
may never be: the thigh is posed (two markers and the hip) while the ankle marker is hidden, the shank's two markers
are seen while the thigh marker is hidden, and the foot, a triangle that fits the other foot as well, waits for the
shank. Frame by frame, nothing in it is named. Its markers' trajectories (``label_sequence``) each keep one marker
throughout, though, so what the frames tell one at a time adds up along them: the shin marker's trajectory keeps its
distance to the knee centre while the thigh is posed, the ankle marker's its distance to the shin marker while both
are seen, and three trajectories at the foot's layout put the ankle centre, once, where the shank's markers keep
their distances to it.

:func:`name_by_evidence` names such trajectories, round after round, each round's names checking the next's. A part
of a trajectory left unnamed takes a marker's name when the frames that check it (its distances to the segment's
markers named there, and to its joint centres where a neighbour is posed) agree in nearly all of them and in enough of
them, and no other part could take that name in those frames, nor that part another name. Three parts none of whose
segment's markers is named take three of its names when they keep its layout's distances and the segment placed on
them puts a joint centre where the neighbour's named markers keep their distances to it. What does not check a name:
a frame where the segment's named markers break its layout; a joint centre that may stray more than ``joint_mm``; a
distance to a mate named in the part's frames, unless the frames refute that the two names are swapped.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from itertools import combinations
from typing import Protocol

import numpy as np
from numba import njit

from mocapflow.mocap.labelling.assignment import distance, norm
from mocapflow.mocap.rigidfit import kabsch, kabsch_into, place

AGREE = 0.9
"""Share of the frames that check a naming in which it must hold."""
CHECKED_S = 0.1
"""Least time (s) over which a naming must be checked, and hold."""


Reference = tuple[np.ndarray, float, np.ndarray]
"""What checks a point in each frame: where it is (F, 3; NaN where unknown), the point's distance to it and the
tolerance on that distance (F,)."""


class Segment(Protocol):
    """A segment of the labeller from a skeleton: its markers' indices, their layout in its frame ``(n, 3)`` and
    tolerances (mm), its joints (neighbour, centre in this frame, centre in the neighbour's, tolerance), and between
    each two of its markers the layout's distance ``sides`` (n, n) and how far two points keeping it may stray
    ``slack`` (n, n: their tolerances together)."""

    markers: np.ndarray
    local: np.ndarray
    tol: np.ndarray
    joints: list[tuple[int, np.ndarray, np.ndarray, float]]
    sides: np.ndarray
    slack: np.ndarray


@dataclass
class Tables:
    """Segments (``Segment``) as arrays, for compiled code: per segment its first marker and how many (a segment's
    markers follow one another); per marker its place in the layout (N, 3) and its tolerance (N,); per joint of each
    segment, each segment's together from ``joint_first[s]`` (S + 1,) in its ``joints`` order: the neighbour, the
    centre in the segment and in the neighbour (J, 3), and the joint's tolerance."""

    first: np.ndarray
    count: np.ndarray
    local: np.ndarray
    tol: np.ndarray
    joint_first: np.ndarray
    other: np.ndarray
    here: np.ndarray
    there: np.ndarray
    joint_tol: np.ndarray

    @classmethod
    def of(cls, segments: Sequence[Segment]) -> Tables:
        joints = [joint for seg in segments for joint in seg.joints]
        return cls(np.array([seg.markers[0] for seg in segments], np.intp),
                   np.array([len(seg.markers) for seg in segments], np.intp),
                   np.concatenate([seg.local for seg in segments]).astype(np.float64),
                   np.concatenate([seg.tol for seg in segments]).astype(np.float64),
                   np.cumsum([0] + [len(seg.joints) for seg in segments]).astype(np.intp),
                   np.array([other for other, *_ in joints], np.intp),
                   np.array([here for _, here, _, _ in joints], np.float64).reshape(-1, 3),
                   np.array([there for _, _, there, _ in joints], np.float64).reshape(-1, 3),
                   np.array([tol for *_, tol in joints], np.float64))


def name_by_evidence(positions: np.ndarray, owner: np.ndarray, segments: Sequence[Segment],
                     snug: dict[tuple[int, int], float], rate: float, joint_mm: float) -> np.ndarray:
    """``owner`` (F, T), the marker each trajectory point of ``positions`` (F, T, 3) is named (-1 for none), with the
    unnamed parts of trajectories named where the frames that check them agree (see the module). ``snug``: per joint
    (both ways), how far apart its two segments may put its centre (mm); a segment posed through joints whose centres
    may stray farther than ``joint_mm`` all told checks nothing."""
    owner = owner.copy()
    least = max(3, int(round(CHECKED_S * rate)))
    markers = sum(len(seg.markers) for seg in segments)
    seen = np.isfinite(positions[..., 0])
    tables = Tables.of(segments)
    joints = [(s, other) for s, seg in enumerate(segments) for other, _, _, _ in seg.joints]  # in ``tables`` order
    joint_snug = _joint_snug(segments, snug)
    while True:
        named = _named_positions(positions, owner, markers)
        # per joint (segment, neighbour): where the neighbour puts its centre in each frame, and how far it may stray
        where, tol = np.full((len(named), len(joints), 3), np.nan), np.zeros((len(named), len(joints)))
        for f in range(len(named)):
            _place_centres(named[f], np.zeros((len(segments), 3, 3)), np.zeros((len(segments), 3)),
                           np.zeros(len(segments), np.bool_), tables.first, tables.count, tables.local, tables.tol,
                           tables.joint_first, tables.other, tables.here, tables.there, joint_snug, float(joint_mm),
                           where[f], tol[f])
        centres = {joint: (where[:, j], tol[:, j]) for j, joint in enumerate(joints)}
        open_part = seen & (owner < 0)
        given = _by_references(positions, open_part, named, centres, segments, least)
        if not given:
            given = _by_layout(positions, open_part, named, centres, segments, snug, joint_mm, least)
        if not given:
            return owner
        for track, marker in given:
            free = open_part[:, track] & np.isnan(named[:, marker, 0])
            owner[free, track] = marker


def _joint_snug(segments: Sequence[Segment], snug: dict[tuple[int, int], float]) -> np.ndarray:
    """Per joint, in ``Tables`` order (each segment's joints in turn), how far apart its two segments may put its
    centre (``snug``)."""
    return np.array([snug[s, other] for s, seg in enumerate(segments) for other, _, _, _ in seg.joints], np.float64)


def _named_positions(positions: np.ndarray, owner: np.ndarray, markers: int) -> np.ndarray:
    """Each marker's position in each frame (F, N, 3) from the trajectories named it; NaN where none is."""
    named = np.full((len(owner), markers, 3), np.nan)
    f, k = np.nonzero(owner >= 0)
    named[f, owner[f, k]] = positions[f, k]
    return named


def _references(s: int, row: int, named: np.ndarray, centres: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]],
                segments: Sequence[Segment], but: int = -1) -> list[Reference]:
    """What checks marker ``row`` of segment ``s``: its segment's markers named (but the one of row ``but``), and the
    centres of its joints to posed neighbours."""
    seg = segments[s]
    frames = len(named)
    out = []
    for j, mate in enumerate(seg.markers):
        if j not in (row, but):
            out.append((named[:, mate], float(np.linalg.norm(seg.local[row] - seg.local[j])),
                        np.full(frames, seg.tol[row] + seg.tol[j])))
    for other, here, _, _ in seg.joints:
        centre, tol = centres[s, other]
        out.append((centre, float(np.linalg.norm(seg.local[row] - here)), seg.tol[row] + tol))
    return out


class _Garbled:
    """Tells, per frame, the segments whose named markers break their layout: two of them farther from their layout
    distance than their tolerances allow (names that check nothing)."""

    def __init__(self, segments: Sequence[Segment]) -> None:
        rows = [(s, seg, i, j) for s, seg in enumerate(segments) for i, j in combinations(range(len(seg.markers)), 2)]
        self.pairs = np.array([(seg.markers[i], seg.markers[j]) for _, seg, i, j in rows], np.intp).reshape(-1, 2)
        self.distance = np.array([seg.sides[i, j] for _, seg, i, j in rows])
        self.tol = np.array([seg.slack[i, j] for _, seg, i, j in rows])
        self.segment = np.array([s for s, *_ in rows], np.intp)  # pair -> its segment
        self.count = len(segments)  # segments

    def __call__(self, named: np.ndarray) -> np.ndarray:
        """(..., S) from the markers' positions ``named`` (..., N, 3), NaN where not named."""
        frames = np.ascontiguousarray(named, dtype=np.float64).reshape(-1, *named.shape[-2:])
        out = np.zeros((len(frames), self.count), np.bool_)
        _broken(frames, self.pairs, self.distance, self.tol, self.segment, out)
        return out.reshape(*named.shape[:-2], self.count)


@njit(cache=True)
def _broken(named: np.ndarray, pairs: np.ndarray, apart: np.ndarray, tol: np.ndarray, segment: np.ndarray,
            out: np.ndarray) -> None:  # pragma: no cover
    """``_Garbled``, compiled, into ``out`` (F, S) (all False given): per frame of ``named`` (F, N, 3), the segments
    with a pair of named markers farther than ``tol`` from their distance ``apart`` (not where either is NaN)."""
    for f in range(len(named)):
        for k in range(len(pairs)):
            if abs(distance(named[f, pairs[k, 0]], named[f, pairs[k, 1]]) - apart[k]) > tol[k]:
                out[f, segment[k]] = True


def _verdicts(points: np.ndarray, references: list[Reference]) -> tuple[np.ndarray, np.ndarray]:
    """Per frame and point (``points`` (F, 3) or (F, T, 3)): whether some reference checks it, and whether one it
    fails."""
    checked = np.zeros(points.shape[:-1], bool)
    failed = np.zeros(points.shape[:-1], bool)
    for where, apart, tol in references:
        shape = (-1,) + (1,) * (points.ndim - 2)
        d = norm(points - where.reshape(shape + (3,)))
        known = np.isfinite(d)
        checked |= known
        failed |= known & (np.abs(d - apart) > tol.reshape(shape))
    return checked, failed


def _by_references(positions: np.ndarray, open_part: np.ndarray, named: np.ndarray,
                   centres: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]], segments: Sequence[Segment],
                   least: int) -> list[tuple[int, int]]:
    """(trajectory, marker) namings of unnamed trajectory parts by their distances to what is known of the marker's
    segment (its named markers, its joint centres), frame by frame.

    A part seen in no frame where the marker is named agrees with it when the checks hold (a frame where the
    segment's named markers break its layout fails them). Two markers keep one distance whichever is which, so a
    part beside a mate named in its frames could be that mate, the mate's point being the marker (two names the
    passes swapped): the part takes the name only when the frames refute that, either the part checked as the mate
    or the mate's point as the marker."""
    own = np.where(open_part[..., None], positions, np.nan)
    agrees = np.zeros((named.shape[1], open_part.shape[1]), bool)
    refuted = np.zeros_like(agrees)
    swapped = np.zeros((named.shape[1],) * 2, bool)  # [m, n]: the frames refute that n's point is m
    garbled = _Garbled(segments)(named)
    for s, seg in enumerate(segments):
        doubt = garbled[:, s]
        for row, marker in enumerate(seg.markers):
            checked, failed = _verdicts(own, _references(s, row, named, centres, segments))
            failed |= checked & doubt[:, None]
            agrees[marker], refuted[marker] = _agrees(checked, failed, least)
            for j, mate in enumerate(seg.markers):
                if j != row:
                    checked, failed = _verdicts(named[:, mate], _references(s, row, named, centres, segments, j))
                    swapped[marker, mate] = _agrees(checked, failed, least)[1]
    held = np.isfinite(named[..., 0])
    # per marker and part: whether the marker is named in a frame the part is seen unnamed (another marker's part)
    overlaps = (held.T.astype(np.int64) @ open_part.astype(np.int64)) > 0
    agree = []
    for marker, k in np.argwhere(agrees & ~overlaps & open_part.any(axis=0)):
        mates = next(one.markers for one in segments if marker in one.markers)
        beside = mates[overlaps[mates, k]]
        if (refuted[beside, k] | swapped[marker, beside]).all():
            agree.append((int(k), int(marker)))
    return _unique(agree, open_part)


def _agrees(checked: np.ndarray, failed: np.ndarray, least: int) -> tuple[np.ndarray, np.ndarray]:
    """Whether the checks (per frame, and per point if 2-D) hold in nearly every frame that checks them, and in
    ``least`` frames or more; whether they fail in more than that allows, over ``least`` frames or more."""
    count = checked.sum(axis=0)
    bad = failed.sum(axis=0)
    return (count - bad >= least) & (bad <= (1 - AGREE) * count), (count >= least) & (bad > (1 - AGREE) * count)


def _unique(agree: list[tuple[int, int]], open_part: np.ndarray) -> list[tuple[int, int]]:
    """The namings of ``agree`` whose trajectory part agrees with no other marker and whose marker with no other
    part seen in the same frames."""
    tracks = [k for k, _ in agree]
    out = []
    for k, m in agree:
        if tracks.count(k) > 1:
            continue
        rivals = [q for q, n in agree if n == m and q != k]
        if any((open_part[:, q] & open_part[:, k]).any() for q in rivals):
            continue
        out.append((k, m))
    return out


def _by_layout(positions: np.ndarray, open_part: np.ndarray, named: np.ndarray,
               centres: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]], segments: Sequence[Segment],
               snug: dict[tuple[int, int], float], most: float, least: int) -> list[tuple[int, int]]:
    """Namings of three unnamed trajectory parts as three markers of a segment none of whose markers is named: their
    distances keep the layout's, and the segment placed on them puts a joint centre where its neighbour's named
    markers keep their distances to it (or where the posed neighbour puts it). A triangle fits its mirror image, the
    other side's segment: the joint centre tells them apart, through a joint whose two segments put its centre
    within ``most`` of each other (``snug``). Of a segment of four markers or more, any three of its markers may be
    named so, as long as no part is given two of them and no marker two parts."""
    agree: list[tuple[int, int, int]] = []  # (part, segment, layout row)
    parts = np.flatnonzero(open_part.sum(axis=0) >= least)
    pos = np.where(open_part[..., None], positions, np.nan)[:, parts]
    for s, seg in enumerate(segments):
        if len(seg.markers) < 3 or not seg.joints or np.isfinite(named[:, seg.markers, 0]).any():
            continue
        for rows in combinations(range(len(seg.markers)), 3):
            for trio in _trios(pos, seg, rows, least):
                ks = [int(parts[i]) for i in trio]
                both = open_part[:, ks].all(axis=1)
                lay = np.broadcast_to(seg.local[list(rows)], (int(both.sum()), 3, 3))
                r, t, ok = kabsch(lay, positions[both][:, ks], np.ones((len(lay), 3)))
                checked = np.zeros(len(lay), bool)
                failed = np.zeros(len(lay), bool)
                for other, here, there, _ in seg.joints:
                    if snug[s, other] > most:
                        continue
                    centre = np.where(ok[:, None], np.einsum("fij,j->fi", r, here) + t, np.nan)
                    o = segments[other]
                    where, tol = centres[s, other]
                    refs = [(named[both, m], float(np.linalg.norm(o.local[i] - there)),
                             np.full(len(lay), o.tol[i] + snug[s, other])) for i, m in enumerate(o.markers)]
                    refs.append((where[both], 0.0, tol[both]))
                    one, wrong = _verdicts(centre, refs)
                    checked |= one
                    failed |= wrong
                if _agrees(checked, failed, least)[0]:
                    agree += [(k, s, row) for k, row in zip(ks, rows, strict=True)]
    out = []
    for k, s, row in set(agree):
        if all(k != q or (s, row) == (n, w) for q, n, w in agree) and \
                all(s != n or (k == q) == (row == w) for q, n, w in agree):
            out.append((k, int(segments[s].markers[row])))
    return out


def _trios(pos: np.ndarray, seg: Segment, rows: tuple[int, int, int], least: int) -> list[tuple[int, int, int]]:
    """Three trajectory parts (columns of ``pos`` (F, P, 3), in layout-row order) whose distances keep the layout's
    between ``rows`` in nearly every frame all three are seen, and in enough of them."""
    a, b, c = rows
    ab, bc, ac = (_keeps(pos, float(seg.sides[i, j]), seg.slack[i, j], least) for i, j in ((a, b), (b, c), (a, c)))
    return [(int(i), int(j), int(k)) for i, j in np.argwhere(ab) for k in np.flatnonzero(bc[j] & ac[i])
            if len({i, j, k}) == 3]


def _keeps(pos: np.ndarray, distance: float, tol: float, least: int, chunk: int = 256) -> np.ndarray:
    """(P, P): whether two columns of ``pos`` (F, P, 3) keep ``distance`` (within ``tol``) in nearly every frame both
    are seen, and in ``least`` frames or more."""
    good = np.zeros((pos.shape[1],) * 2, np.int64)
    known = np.zeros_like(good)
    for start in range(0, len(pos), chunk):
        part = pos[start:start + chunk]
        d = norm(part[:, :, None] - part[:, None, :])
        seen = np.isfinite(d)
        known += seen.sum(axis=0)
        good += (seen & (np.abs(d - distance) <= tol)).sum(axis=0)
    return (good >= least) & (good >= AGREE * known)


class RunningEvidence:
    """The same evidence gathered frame by frame, as far as the frames so far tell (``TrackedModelLabeller``): per
    track and marker, over the track's current run (the frames it has been seen in a row, one marker surely), the
    frames that check the track's point as that marker, and those whose checks it fails.

    A frame checks a point as a marker when it knows the distances to two of the marker's mates named there, or to
    the centre of one of the segment's joints, the neighbour posed (by three of its markers or more, or, as over a
    whole recording, by its named markers and the centres of its joints to posed segments); the other distances it
    knows then check the point too. A frame where a check fails counts as well. The distance to one mate alone checks
    too little over a run's first frames: a point of the next segment keeps it for a while as well. A run takes a
    marker's name when the checks hold in nearly all of at least ``CHECKED_S`` of frames (``AGREE``), it agrees with
    no other marker, no other run seen now agrees with that marker, and the marker was named elsewhere in none of the
    run's frames. Three runs no such check names may take three names of a segment none of whose markers is named by
    its layout (:meth:`layouts`). A run keeps its name while its checks do not refute it (:meth:`refuted`)."""

    def __init__(self, segments: Sequence[Segment], snug: dict[tuple[int, int], float], rate: float,
                 joint_mm: float) -> None:
        self.segments, self.snug, self.joint_mm = segments, snug, joint_mm
        self.least = max(3, int(round(CHECKED_S * rate)))
        markers = sum(len(seg.markers) for seg in segments)
        self._segment_of = np.empty(markers, np.intp)
        for s, seg in enumerate(segments):
            self._segment_of[seg.markers] = s
        self._joints = [(s, other, there) for s, seg in enumerate(segments) for other, _, there, _ in seg.joints]
        # for the compiled placement of the joint centres (``_centres``): the segments as arrays, and per joint, in
        # ``_joints`` order, how far apart the two segments put its centre (``snug``)
        self._tables = Tables.of(segments)
        self._joint_snug = _joint_snug(segments, snug)
        # per marker, its references as rows of a frame's places (its markers named, then its joints' centres, then
        # a row of NaN for padding), the distance to each and the marker's own share of the tolerance
        width = max(len(seg.markers) - 1 + len(seg.joints) for seg in segments)
        self._ref = np.full((markers, width), markers + len(self._joints), np.intp)
        self._distance = np.zeros((markers, width))
        self._tol = np.zeros((markers, width))
        joint = 0
        for seg in segments:
            for row, marker in enumerate(seg.markers):
                refs = [(int(mate), seg.local[j], seg.tol[row] + seg.tol[j])
                        for j, mate in enumerate(seg.markers) if j != row]
                refs += [(markers + joint + k, here, seg.tol[row]) for k, (_, here, _, _) in enumerate(seg.joints)]
                for k, (ref, where, tol) in enumerate(refs):
                    self._ref[marker, k] = ref
                    self._distance[marker, k] = np.linalg.norm(seg.local[row] - where)
                    self._tol[marker, k] = tol
            joint += len(seg.joints)
        self._centre = (self._ref >= markers) & (self._ref < markers + len(self._joints))
        self._garbled = _Garbled(segments)
        self.checked = np.zeros((0, markers), np.int64)
        self.failed = np.zeros((0, markers), np.int64)
        self.overlap = np.zeros((0, markers), bool)  # the marker named elsewhere in a frame of the run
        # per (segment, layout rows, tracks) of three runs at a layout's distances: frames checked, and failed
        self._trios: dict[tuple[int, tuple[int, int, int], tuple[int, int, int]], np.ndarray] = {}
        # the frame's joint centres and their tolerances (``_centres``), as ``add`` last placed them
        self._placed = np.full((len(self._joints), 3), np.nan), np.zeros(len(self._joints))

    def grow(self, tracks: int) -> None:
        """Room for ``tracks`` tracks in all."""
        more = tracks - len(self.checked)
        if more > 0:
            markers = self.checked.shape[1]
            self.checked = np.vstack([self.checked, np.zeros((more, markers), np.int64)])
            self.failed = np.vstack([self.failed, np.zeros((more, markers), np.int64)])
            self.overlap = np.vstack([self.overlap, np.zeros((more, markers), bool)])

    def restart(self, tracks: np.ndarray) -> None:
        """Forget what the runs of ``tracks`` gathered: they start a new run."""
        self.checked[tracks], self.failed[tracks], self.overlap[tracks] = 0, 0, False
        if len(tracks) and self._trios:
            gone = set(tracks.tolist())
            self._trios = {key: count for key, count in self._trios.items() if not gone & set(key[2])}

    def add(self, points: np.ndarray, tracks: np.ndarray, named: np.ndarray, rot: np.ndarray, shift: np.ndarray,
            posed: np.ndarray, level: np.ndarray) -> None:
        """Gather one frame: ``points`` (P, 3) on ``tracks`` (P,), named by nothing but this evidence; ``named``
        (N, 3) the markers named otherwise in the frame (NaN where none is); each segment's pose, ``rot`` (S, 3, 3)
        and ``shift`` (S, 3) where ``posed`` (S,), and ``level`` how it was posed (0: by three markers or more)."""
        held = np.isfinite(named[:, 0])
        self.overlap[np.ix_(tracks, held)] = True
        centres, centre_tol = self._centres(named, rot, shift, posed & (level == 0))
        self._placed = centres, centre_tol
        places = np.concatenate([named, centres, np.full((1, 3), np.nan)])
        tol = self._tol + np.concatenate([np.zeros(len(named)), centre_tol, [0.0]])[self._ref]
        checked, failed = np.empty((len(points), len(named)), np.bool_), np.empty((len(points), len(named)), np.bool_)
        _check(np.ascontiguousarray(points, dtype=np.float64), places, self._ref, self._distance, tol, self._centre,
               checked, failed)
        self.checked[tracks] += checked
        self.failed[tracks] += failed | (checked & self._garbled(named)[self._segment_of])

    def _centres(self, named: np.ndarray, rot: np.ndarray, shift: np.ndarray,
                 posed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where each joint's neighbour puts its centre (J, 3), and how far the centre may stray (J,); NaN where the
        neighbour is not posed, or where that is farther than ``joint_mm``. A segment ``posed`` (by three markers or
        more: ``rot``, ``shift``) stands; the others are posed as over a whole recording (``_place_centres``), from
        their markers ``named`` and the centres of their joints to posed segments."""
        centres, tol = np.full((len(self._joints), 3), np.nan), np.zeros(len(self._joints))
        tables = self._tables
        _place_centres(np.ascontiguousarray(named, dtype=np.float64), rot.copy(), shift.copy(), posed.copy(),
                       tables.first, tables.count, tables.local, tables.tol, tables.joint_first, tables.other,
                       tables.here, tables.there, self._joint_snug, float(self.joint_mm), centres, tol)
        return centres, tol

    def refuted(self, tracks: np.ndarray) -> np.ndarray:
        """(T, N): whether the checks of each of ``tracks`` as each marker failed in more frames than agreeing
        allows."""
        count, bad = self.checked[tracks], self.failed[tracks]
        return (count >= self.least) & (bad > (1 - AGREE) * count)

    def layouts(self, points: np.ndarray, tracks: np.ndarray, named: np.ndarray,
                free: np.ndarray) -> list[tuple[int, int]]:
        """(index into ``points``, marker) namings of three runs as three markers of a segment none of whose markers
        is named (``named``, all the frame's names), gathering this frame (``points`` (P, 3) on ``tracks``, unnamed,
        after ``add``): as over a whole recording (``_by_layout``), three points at the layout's distances whose
        placed segment puts a joint centre where the neighbour's named markers keep their distances to it, or where
        the posed neighbour puts it, in nearly all of ``CHECKED_S`` of frames or more. A triangle fits its mirror
        image; the joint tells them apart. Taken when no run of them agrees with another place in a layout, no place
        with another run, the names are ``free``, and no run's own checks refute its name nor was it named elsewhere
        in a frame of the run."""
        seen = set(tracks.tolist())  # a trio gathers while its three runs are seen unnamed
        self._trios = {key: count for key, count in self._trios.items() if seen >= set(key[2])}
        if len(points) < 3:
            return []
        centres, centre_tol = self._placed
        d = norm(points[:, None] - points[None])
        joint = 0
        for s, seg in enumerate(self.segments):
            first = joint
            joint += len(seg.joints)
            if len(seg.markers) < 3 or np.isfinite(named[seg.markers, 0]).any():
                continue
            # per joint its centre would check: where the neighbour's named markers and posed centre are, the centre's
            # distances to them and their tolerances
            refs: list[tuple[np.ndarray, np.ndarray, float, float]] = []
            for k, (other, here, there, _) in enumerate(seg.joints):
                o = self.segments[other]
                where = np.concatenate([named[o.markers], centres[first + k][None]])
                known = np.isfinite(where[:, 0])
                if self.snug[s, other] <= self.joint_mm and known.any():
                    refs += zip(np.repeat(here[None], known.sum(), axis=0), where[known],
                                np.append(norm(o.local - there), 0.0)[known],
                                np.append(o.tol + self.snug[s, other], centre_tol[first + k])[known], strict=True)
            if not refs:
                continue
            centre_here, centre_where, want, tol = (np.array([ref[i] for ref in refs], np.float64) for i in range(4))
            for rows in combinations(range(len(seg.markers)), 3):
                trios, failed = _trios_placed(np.ascontiguousarray(points, dtype=np.float64), d,
                                              seg.local[list(rows)], seg.sides[np.ix_(rows, rows)],
                                              seg.slack[np.ix_(rows, rows)], centre_here, centre_where, want, tol)
                for trio, bad in zip(trios, failed, strict=True):
                    key = (s, rows, (int(tracks[trio[0]]), int(tracks[trio[1]]), int(tracks[trio[2]])))
                    self._trios.setdefault(key, np.zeros(2, np.int64))[:] += (1, int(bad))
        agree = [key for key, (count, bad) in self._trios.items()
                 if count - bad >= self.least and bad <= (1 - AGREE) * count]
        place = [(track, s, row) for s, rows, trio in agree for track, row in zip(trio, rows, strict=True)]
        index = {int(t): i for i, t in enumerate(tracks)}
        refuted = self.refuted(tracks)
        out = []
        for track, s, row in set(place):
            if all(track != q or (s, row) == (n, w) for q, n, w in place) and \
                    all(s != n or row != w or track == q for q, n, w in place):
                marker = int(self.segments[s].markers[row])
                if free[marker] and not self.overlap[track, marker] and not refuted[index[track], marker]:
                    out.append((index[track], marker))
        return out

    def agreed(self, tracks: np.ndarray) -> np.ndarray:
        """(T, N): whether each of ``tracks`` agrees with each marker so far."""
        count, bad = self.checked[tracks], self.failed[tracks]
        return (count - bad >= self.least) & (bad <= (1 - AGREE) * count)

    def names(self, tracks: np.ndarray, free: np.ndarray) -> np.ndarray:
        """The marker each of ``tracks`` (those seen now, named by nothing else) is to take, -1 for none: the only one
        it agrees with, which no other of them agrees with, named elsewhere in none of its run's frames and ``free``
        now."""
        agree = self.agreed(tracks)
        unique = agree & (agree.sum(axis=1, keepdims=True) == 1) & (agree.sum(axis=0, keepdims=True) == 1)
        ok = unique & ~self.overlap[tracks] & free[None]
        return np.where(ok.any(axis=1), ok.argmax(axis=1), -1)


@njit(cache=True)
def _place_centres(named: np.ndarray, rot: np.ndarray, shift: np.ndarray, posed: np.ndarray, first: np.ndarray,
                   count: np.ndarray, local: np.ndarray, marker_tol: np.ndarray, joint_first: np.ndarray,
                   other: np.ndarray, here: np.ndarray, there: np.ndarray, snug: np.ndarray, joint_mm: float,
                   centres: np.ndarray, tol: np.ndarray) -> None:  # pragma: no cover
    """One frame's joint centres into ``centres`` (J, 3) and how far each may stray into ``tol`` (J,), for
    ``name_by_evidence`` (no segment posed beforehand) and ``RunningEvidence._centres``: the segments posed (``posed``,
    ``rot``, ``shift``, changed in place) stand; round after round, each other segment with a marker ``named`` is
    fitted to its named markers and the centres of its joints to posed neighbours held within ``joint_mm`` (three or
    more in all), and posed where each of those lies within its tolerance of the fit, its slack the largest of those
    joints' (a centre it places is only as sure as they are); then each joint's centre is placed by its posed
    neighbour, within ``snug`` plus that neighbour's slack."""
    segments = len(first)
    slack = np.zeros(segments)
    have = np.zeros(segments, np.int64)
    width = 0
    for s in range(segments):
        for m in range(first[s], first[s] + count[s]):
            if np.isfinite(named[m, 0]):
                have[s] += 1
        width = max(width, count[s] + joint_first[s + 1] - joint_first[s])
    lay, x, limit = np.empty((width, 3)), np.empty((width, 3)), np.empty(width)
    r, t, at = np.empty((3, 3)), np.empty(3), np.empty(3)
    stale = np.ones(segments, np.bool_)  # a segment is fitted again only once a neighbour has been posed
    changed = True
    while changed:
        changed = False
        for s in range(segments):
            if posed[s] or have[s] == 0 or not stale[s]:
                continue
            stale[s] = False
            k = 0
            for m in range(first[s], first[s] + count[s]):
                if np.isfinite(named[m, 0]):
                    lay[k], x[k], limit[k] = local[m], named[m], marker_tol[m]
                    k += 1
            most = 0.0
            for j in range(joint_first[s], joint_first[s + 1]):
                o = other[j]
                held = snug[j] + slack[o]
                if posed[o] and held <= joint_mm:
                    lay[k], limit[k] = here[j], held
                    place(rot[o], there[j], shift[o], x[k])
                    most = max(most, held)
                    k += 1
            if k < 3 or not kabsch_into(lay[:k], x[:k], np.full(k, 1.0 / k), r, t):
                continue
            fits = True
            for n in range(k):
                place(r, lay[n], t, at)
                fits = fits and distance(at, x[n]) <= limit[n]
            if fits:
                rot[s], shift[s], posed[s], slack[s] = r, t, True, most
                changed = True
                for j in range(joint_first[s], joint_first[s + 1]):
                    stale[other[j]] = True
    for s in range(segments):
        for j in range(joint_first[s], joint_first[s + 1]):
            o = other[j]
            held = snug[j] + slack[o]
            if posed[o] and held <= joint_mm:
                place(rot[o], there[j], shift[o], centres[j])
                tol[j] = held


@njit(cache=True)
def _check(points: np.ndarray, places: np.ndarray, ref: np.ndarray, apart: np.ndarray, tol: np.ndarray,
           centre: np.ndarray, checked: np.ndarray, failed: np.ndarray) -> None:  # pragma: no cover
    """For ``RunningEvidence.add``, per point (P) and marker (N), into ``checked`` and ``failed`` (P, N): whether the
    point's distances to the marker's references (``places[ref]``, NaN where unknown) fail one (off ``apart`` by more
    than ``tol``), and whether they check it (a joint centre, two mates, or a failure)."""
    for p in range(len(points)):
        for n in range(ref.shape[0]):
            fails, by_centre, mates = False, False, 0
            for r in range(ref.shape[1]):
                d = distance(points[p], places[ref[n, r]])
                if np.isfinite(d):
                    fails = fails or abs(d - apart[n, r]) > tol[n, r]
                    by_centre = by_centre or centre[n, r]
                    mates += not centre[n, r]
            failed[p, n] = fails
            checked[p, n] = by_centre or mates >= 2 or fails


@njit(cache=True)
def _trios_placed(points: np.ndarray, d: np.ndarray, lay: np.ndarray, sides: np.ndarray, slack: np.ndarray,
                  centre_here: np.ndarray, centre_where: np.ndarray, want: np.ndarray,
                  tol: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """For ``RunningEvidence.layouts``: every three distinct ``points`` (``d`` their distances) at the distances of
    three layout rows (``lay`` (3, 3), their ``sides`` and ``slack`` (3, 3)), in the order of the rows' pairs, whose
    placement of the rows fixes a rotation: the trios (T, 3), and whether the placement puts a joint centre
    (``centre_here``, one row per reference) off its distance ``want`` from a reference ``centre_where`` by more
    than ``tol``."""
    n = len(points)
    first = np.abs(d - sides[0, 1]) <= slack[0, 1]  # pairs at the first two rows' distance: n trios each at most
    trios = np.empty((first.sum() * n, 3), np.intp)
    failed = np.empty(first.sum() * n, np.bool_)
    x = np.empty((3, 3))
    weight = np.full(3, 1.0 / 3.0)
    r, t, at = np.empty((3, 3)), np.empty(3), np.empty(3)
    found = 0
    for i in range(n):
        for j in range(n):
            if not first[i, j]:
                continue
            for k in range(n):
                if not (abs(d[j, k] - sides[1, 2]) <= slack[1, 2] and abs(d[i, k] - sides[0, 2]) <= slack[0, 2]):
                    continue
                if i == j or j == k or i == k:
                    continue
                x[0], x[1], x[2] = points[i], points[j], points[k]
                if not kabsch_into(lay, x, weight, r, t):
                    continue
                bad = False
                for q in range(len(want)):
                    place(r, centre_here[q], t, at)
                    bad = bad or abs(distance(at, centre_where[q]) - want[q]) > tol[q]
                trios[found, 0], trios[found, 1], trios[found, 2] = i, j, k
                failed[found] = bad
                found += 1
    return trios[:found], failed[:found]
