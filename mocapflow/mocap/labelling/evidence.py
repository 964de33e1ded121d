"""Naming trajectories from a skeleton where no single frame can: evidence gathered over their whole length.

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

from mocapflow.mocap.labelling.assignment import norm
from mocapflow.mocap.rigidfit import kabsch

AGREE = 0.9
"""Share of the frames that check a naming in which it must hold."""
CHECKED_S = 0.1
"""Least time (s) over which a naming must be checked, and hold."""


@dataclass
class Pose:
    """A segment's pose in each frame: ``world = rot @ local + shift`` where ``posed``; ``slack`` (mm) is how far a
    point it places may stray beyond its own tolerance (0 where posed by its markers alone)."""

    rot: np.ndarray  # (F, 3, 3)
    shift: np.ndarray  # (F, 3)
    posed: np.ndarray  # (F,)
    slack: np.ndarray  # (F,)

    def centre(self, local: np.ndarray, snug: float, most: float) -> tuple[np.ndarray, np.ndarray]:
        """Where the pose puts a joint centre ``local`` in each frame (F, 3), and how far from there the other segment
        may put it (F,): ``snug`` and the slack; NaN where not posed, or where that is farther than ``most``."""
        tol = snug + self.slack
        where = self.posed & (tol <= most)
        return np.where(where[:, None], np.einsum("fij,j->fi", self.rot, local) + self.shift, np.nan), tol


Reference = tuple[np.ndarray, float, np.ndarray]
"""What checks a point in each frame: where it is (F, 3; NaN where unknown), the point's distance to it and the
tolerance on that distance (F,)."""


class Segment(Protocol):
    """A segment of the labeller from a skeleton: its markers' indices, their layout in its frame ``(n, 3)`` and
    tolerances (mm), and its joints (neighbour, centre in this frame, centre in the neighbour's, tolerance)."""

    markers: np.ndarray
    local: np.ndarray
    tol: np.ndarray
    joints: list[tuple[int, np.ndarray, np.ndarray, float]]


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
    while True:
        named = _named_positions(positions, owner, markers)
        poses = _poses(named, segments, snug, joint_mm)
        # per joint (segment, neighbour): where the neighbour puts its centre, and how far it may stray
        centres = {(s, other): poses[other].centre(there, snug[s, other], joint_mm)
                   for s, seg in enumerate(segments) for other, _, there, _ in seg.joints}
        open_part = seen & (owner < 0)
        given = _by_references(positions, open_part, named, centres, segments, least)
        if not given:
            given = _by_layout(positions, open_part, named, centres, segments, snug, joint_mm, least)
        if not given:
            return owner
        for track, marker in given:
            free = open_part[:, track] & np.isnan(named[:, marker, 0])
            owner[free, track] = marker


def _named_positions(positions: np.ndarray, owner: np.ndarray, markers: int) -> np.ndarray:
    """Each marker's position in each frame (F, N, 3) from the trajectories named it; NaN where none is."""
    named = np.full((len(owner), markers, 3), np.nan)
    f, k = np.nonzero(owner >= 0)
    named[f, owner[f, k]] = positions[f, k]
    return named


def _poses(named: np.ndarray, segments: Sequence[Segment], snug: dict[tuple[int, int], float],
           most_slack: float) -> list[Pose]:
    """Each segment's pose per frame from its named markers and the centres of its joints to segments posed in that
    frame, three references or more with one marker at least, each within its tolerance of the fit; a segment posed
    through a neighbour may pose another in turn. A joint centre placed by a segment posed through joints is only as
    sure as they are: its ``slack`` adds up their tolerances, and a centre that may stray more than ``most_slack`` is
    no reference."""
    frames = len(named)
    out = [Pose(np.zeros((frames, 3, 3)), np.zeros((frames, 3)), np.zeros(frames, bool), np.zeros(frames))
           for _ in segments]
    changed = True
    while changed:
        changed = False
        for s, seg in enumerate(segments):
            pose = out[s]
            local = [seg.local]
            world = [named[:, seg.markers]]
            tol = [np.broadcast_to(seg.tol, (frames, len(seg.markers)))]
            for other, here, there, _ in seg.joints:
                centre, held = out[other].centre(there, snug[s, other], most_slack)
                local.append(here[None])
                world.append(centre[:, None])
                tol.append(held[:, None])
            x = np.concatenate(world, axis=1)
            have = np.isfinite(x[..., 0])
            todo = ~pose.posed & (have.sum(axis=1) >= 3) & have[:, : len(seg.markers)].any(axis=1)
            if not todo.any():
                continue
            lay = np.broadcast_to(np.concatenate(local), x.shape)[todo]
            r, t, ok = kabsch(lay, np.where(have[todo, :, None], x[todo], 0.0), have[todo].astype(float))
            error = norm(np.einsum("fij,fnj->fni", r, lay) + t[:, None] - x[todo])
            limit = np.concatenate(tol, axis=1)[todo]
            ok &= (np.where(have[todo], error, 0.0) <= limit).all(axis=1)
            joints = np.where(have[todo, len(seg.markers):], limit[:, len(seg.markers):], 0.0)
            where = np.flatnonzero(todo)[ok]
            pose.rot[where], pose.shift[where], pose.posed[where] = r[ok], t[ok], True
            pose.slack[where] = joints[ok].max(axis=1, initial=0.0)
            changed |= bool(ok.any())
    return out


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


def _garbled(points: np.ndarray, seg: Segment) -> np.ndarray:
    """Per frame, whether two of a segment's named markers (``points`` (F, n, 3), NaN where not named) are farther
    from their layout distance than their tolerances allow: names that check nothing."""
    pairs = np.array(list(combinations(range(len(seg.markers)), 2)), np.intp).reshape(-1, 2)
    d = norm(points[:, pairs[:, 0]] - points[:, pairs[:, 1]])
    want = norm(seg.local[pairs[:, 0]] - seg.local[pairs[:, 1]])
    return (np.abs(d - want) > seg.tol[pairs[:, 0]] + seg.tol[pairs[:, 1]]).any(axis=1)


def _verdicts(points: np.ndarray, references: list[Reference]) -> tuple[np.ndarray, np.ndarray]:
    """Per frame and point (``points`` (F, 3) or (F, T, 3)): whether some reference checks it, and whether one it
    fails."""
    checked = np.zeros(points.shape[:-1], bool)
    failed = np.zeros(points.shape[:-1], bool)
    for where, distance, tol in references:
        shape = (-1,) + (1,) * (points.ndim - 2)
        d = norm(points - where.reshape(shape + (3,)))
        known = np.isfinite(d)
        checked |= known
        failed |= known & (np.abs(d - distance) > tol.reshape(shape))
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
    for s, seg in enumerate(segments):
        doubt = _garbled(named[:, seg.markers], seg)
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
    ab, bc, ac = (_keeps(pos, float(np.linalg.norm(seg.local[i] - seg.local[j])), seg.tol[i] + seg.tol[j], least)
                  for i, j in ((a, b), (b, c), (a, c)))
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
