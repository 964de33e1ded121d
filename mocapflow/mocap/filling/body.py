"""A skeleton compiled against the filler's label order (``Body``), with the index work of each visibility pattern
kept for reuse (``SegmentFit``, ``Layout``), and the joint centres of a frame from its segments' poses."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple, TypeVar

import numpy as np

from mocapflow.mocap.flags import CASE_OBSERVED
from mocapflow.mocap.model import SkeletonModel
from mocapflow.mocap.rigidfit import RigidFit

_T = TypeVar("_T")
_PATTERNS_KEPT = 64  # visibility patterns whose index work is kept (``recall``)


@dataclass
class BodyJoint:
    parent: int
    child: int
    parent_offset: np.ndarray  # (3,) in the parent's local frame
    child_offset: np.ndarray  # (3,) in the child's local frame


class Body:
    """A skeleton compiled against the filler's label order, padded for batched per-segment work.

    The index work that depends only on which markers are visible (segments near the gaps, pose-fit weights,
    per-segment selections) is kept per visibility pattern (``_recall``): a gap keeps its pattern for many frames.
    """

    def __init__(self, skeleton: SkeletonModel, labels: list[str]) -> None:
        index = {label: i for i, label in enumerate(labels)}
        n = len(labels)
        self.names: list[str] = []
        self.members: list[np.ndarray] = []
        self.offsets: list[np.ndarray] = []
        for seg in skeleton.segments:
            keep = [k for k, m in enumerate(seg.markers) if m in index]
            if len(keep) < 2 or seg.marker_offsets is None:
                continue  # a lone marker or an unknown shape constrains nothing
            self.names.append(seg.name)
            self.members.append(np.array([index[seg.markers[k]] for k in keep]))
            self.offsets.append(np.array([seg.marker_offsets[k] for k in keep], dtype=float))
        s = len(self.members)
        width = max((len(m) for m in self.members), default=0)
        self.idx = np.full((s, width), n)  # padding points at a NaN row appended to positions
        self.local = np.zeros((s, width, 3))
        self.slot = np.zeros((s, width), dtype=bool)
        self.marker_seg = np.full(n, -1)
        self.marker_local = np.zeros((n, 3))  # per marker: its offset in its segment
        for k, (members, offsets) in enumerate(zip(self.members, self.offsets, strict=True)):
            self.idx[k, : len(members)] = members
            self.local[k, : len(members)] = offsets
            self.slot[k, : len(members)] = True
            self.marker_seg[members] = k
            self.marker_local[members] = offsets
        seg_index = {name: k for k, name in enumerate(self.names)}
        self.joint_names: list[str] = []
        self.joints: list[BodyJoint | None] = []  # None: a joint of the skeleton this body cannot use
        self.neighbours: list[list[tuple[int, int]]] = [[] for _ in range(s)]  # (joint, other segment)
        for j in skeleton.joints:
            self.joint_names.append(j.name)
            p, c = seg_index.get(j.parent), seg_index.get(j.child)
            if p is None or c is None or j.parent_offset is None or j.child_offset is None:
                self.joints.append(None)
                continue
            self.joints.append(BodyJoint(p, c, np.array(j.parent_offset, float), np.array(j.child_offset, float)))
            self.neighbours[p].append((len(self.joints) - 1, c))
            self.neighbours[c].append((len(self.joints) - 1, p))
        kinds = [j.kind for j in skeleton.joints]
        for k, links in enumerate(self.neighbours):  # a hinge first, then the parent: the twist reference until the
            # twist statistics have samples
            links.sort(key=lambda link: (kinds[link[0]] != "hinge", self.joint(link[0]).child != k))
        # per segment: (joint, neighbour, centre in this segment's frame, centre in the neighbour's frame)
        self.links = [[(j, other, self.joint_offset(j, k), self.joint_offset(j, other)) for j, other in links]
                      for k, links in enumerate(self.neighbours)]
        # the same, padded for compiled passes: per segment, its links' count, neighbours and the two centres
        most = max(map(len, self.links), default=0)
        self.link_count = np.array(list(map(len, self.links)), dtype=np.int64)
        self.link_other = np.zeros((s, most), dtype=np.int64)
        self.link_own, self.link_theirs = np.zeros((s, most, 3)), np.zeros((s, most, 3))
        for k, centres in enumerate(self.links):
            for i, (_, other, own, theirs) in enumerate(centres):
                self.link_other[k, i], self.link_own[k, i], self.link_theirs[k, i] = other, own, theirs
        self.in_segment = self.marker_seg >= 0
        self.near = np.zeros((n, s), dtype=bool)  # per marker: its segment and that segment's neighbours
        for m, k in enumerate(self.marker_seg):
            if k >= 0:
                self.near[m, [k, *(other for _, other in self.neighbours[k])]] = True
        usable = [j for j in self.joints if j is not None]
        self.joint_usable = np.array([j is not None for j in self.joints], dtype=bool)
        self.joint_segments = np.array([[j.parent, j.child] for j in usable], dtype=int).reshape(-1, 2)
        self.joint_offsets = np.array([[j.parent_offset, j.child_offset] for j in usable]).reshape(-1, 2, 3)
        self._around: dict[bytes, np.ndarray] = {}  # by visibility pattern
        self._fits: dict[bytes, SegmentFit] = {}
        self._layouts: dict[bytes, Layout] = {}

    def joint(self, index: int) -> BodyJoint:
        """A joint this body can use (one named by a segment's ``links``)."""
        jt = self.joints[index]
        assert jt is not None, f"joint {index} is not usable"
        return jt

    def joint_offset(self, joint: int, segment: int) -> np.ndarray:
        """The centre of ``joint`` in ``segment``'s local frame."""
        jt = self.joint(joint)
        return jt.parent_offset if jt.parent == segment else jt.child_offset

    def fit_for(self, use: np.ndarray, segments: np.ndarray) -> SegmentFit:
        """The ``SegmentFit`` of ``segments`` to the markers selected by ``use`` (N,) bool."""
        return recall(self._fits, use.tobytes() + segments.tobytes(), lambda: SegmentFit(self, use, segments))

    def layout(self, visible: np.ndarray, targets: np.ndarray, near: np.ndarray) -> Layout:
        """The ``Layout`` of a visibility pattern."""
        return recall(self._layouts, visible.tobytes() + targets.tobytes() + near.tobytes(),
                       lambda: Layout(self, visible, targets, near))

    def around(self, markers: np.ndarray) -> np.ndarray:
        """Indices of the segments holding any of ``markers`` (N,) bool, and of their neighbours."""
        return recall(self._around, markers.tobytes(), lambda: np.flatnonzero(self.near[markers].any(axis=0)))


def recall(cache: dict[bytes, _T], key: bytes, make: Callable[[], _T]) -> _T:
    """``cache[key]``, made by ``make`` when missing. The keys are visibility patterns (the bytes of boolean masks);
    patterns that do not repeat (scattered dropouts) are dropped by emptying the cache when it is full."""
    value = cache.get(key)
    if value is None:
        if len(cache) >= _PATTERNS_KEPT:
            cache.clear()
        value = cache[key] = make()
    return value


class SegmentFit:
    """The pose fit of some segments to the markers of one visibility pattern: what depends on the pattern alone is
    worked out once (``cor.RigidFit``). ``complete``: the segments with all their markers in the pattern."""

    def __init__(self, body: Body, use: np.ndarray, segments: np.ndarray) -> None:
        idx = body.idx[segments]
        used = np.append(use, False)[idx]
        self.segments = np.asarray(segments, dtype=np.int64)
        self.rows = np.minimum(idx, len(use) - 1)  # (B, M) marker rows, padding on any real row (unused)
        self.rigid = RigidFit(body.local[segments], used.astype(float))
        self.complete = (used | ~body.slot[segments]).all(axis=1)

    def __call__(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """R (B, 3, 3), t (B, 3) and ``ok`` (B,) of the segments fitted to ``positions`` (N, 3); ``ok`` is False where
        the pattern's markers do not fix the pose."""
        return self.rigid(positions[self.rows])  # the markers not used weigh nothing, NaN or not

    def into(self, positions: np.ndarray, r: np.ndarray, t: np.ndarray, ok: np.ndarray) -> None:
        """The same, written into the body's per-segment R (S, 3, 3), t (S, 3) and ``ok`` (S,) at its segments."""
        self.rigid.into(positions, self.rows, self.segments, r, t, ok)


class SegmentPart(NamedTuple):
    """A segment holding a target, in one visibility pattern: its visible markers (rows, offsets, anchor names) and
    its targets (rows, and which of its markers they are)."""

    seen_rows: np.ndarray
    seen_offsets: np.ndarray
    seen_names: list[tuple[str, int]]
    miss: np.ndarray
    hit: np.ndarray


class Anchors(NamedTuple):
    """The points a segment is placed by, in its own frame (``local``), with their weights in the fit and their
    names (``("marker", row)`` or ``("joint", index)``)."""

    local: np.ndarray
    weight: np.ndarray
    names: tuple[tuple[str, int], ...]


class Layout:
    """The index work of ``GapFiller._constrain`` for one visibility pattern (``visible`` markers, ``targets`` to
    estimate, segments ``near`` them).

    ``seg_vis``: visible markers per segment; ``target_rows``, ``target_seg``, ``target_local``: each target's row,
    segment and offset in it; ``segments``: the segments holding a target, ``by_vis`` the same from the most visible
    markers down; ``vis_slot``, ``hit_slot``: per segment and slot of ``Body.idx``, a visible marker, a target;
    ``first``: the segments posed first (``fit_first``), those holding a target, with the other ``near``
    ones when one of those has fewer than three visible markers (it is then placed through its neighbours, so they
    are needed anyway); ``later``: the other ``near`` segments, posed when needed (``fit_later``); ``parts``: per
    segment holding a target, its ``SegmentPart``; ``anchors``: a segment's anchors through given joints.
    """

    def __init__(self, body: Body, visible: np.ndarray, targets: np.ndarray, near: np.ndarray) -> None:
        self.seg_vis = np.bincount(body.marker_seg[visible & body.in_segment], minlength=len(body.members))
        self.target_rows = np.flatnonzero(targets & body.in_segment)
        self.target_seg = body.marker_seg[self.target_rows]
        self.target_local = body.marker_local[self.target_rows]
        self.segments = np.unique(self.target_seg)
        self.by_vis = np.array(sorted(self.segments.tolist(), key=lambda k: -self.seg_vis[k]), dtype=np.int64)
        self.vis_slot = np.append(visible, False)[body.idx]  # per segment and marker slot: visible, a target
        self.hit_slot = np.append(targets, False)[body.idx]
        rest = np.setdiff1d(near, self.segments)
        unposable = (self.seg_vis[self.segments] < 3).any()
        self.first = np.concatenate([self.segments, rest]) if unposable else self.segments
        self.later = rest[:0] if unposable else rest
        self.fit_first = body.fit_for(visible, self.first)
        self.fit_later = body.fit_for(visible, self.later)
        self.parts: dict[int, SegmentPart] = {}
        for k in self.segments.tolist():
            members = body.members[k]
            vis, hit = visible[members], targets[members]
            self.parts[k] = SegmentPart(members[vis], body.offsets[k][vis],
                                        [("marker", x) for x in members[vis].tolist()],
                             members[hit], hit)
        self._anchors: dict[tuple[int, tuple[int, ...]], Anchors] = {}

    def anchors(self, k: int, links: list[tuple[int, int, np.ndarray, np.ndarray]], joint_weight: float) -> Anchors:
        """The anchors of segment ``k`` (one holding a target): its visible markers, then the centres of the joints
        ``links`` (some of ``Body.links[k]``) weighted ``joint_weight``; kept per set of joints."""
        key = (k, tuple(j for j, *_ in links))
        found = self._anchors.get(key)
        if found is None:
            part, nv = self.parts[k], int(self.seg_vis[k])
            local, weight = np.empty((nv + len(links), 3)), np.ones(nv + len(links))
            local[:nv] = part.seen_offsets
            for i, (_, _, own, _) in enumerate(links, start=nv):
                local[i], weight[i] = own, joint_weight
            found = self._anchors[key] = Anchors(local, weight,
                                                 tuple(part.seen_names + [("joint", j) for j, *_ in links]))
        return found


def joint_centres(body: Body, poses: tuple[np.ndarray, np.ndarray, np.ndarray], flags: np.ndarray) -> np.ndarray:
    """Each joint's centre from the poses (R, t, known) of its two segments; from the side whose markers are all
    observed when only one side is (tables 6.1, 6.2: a centre from a segment with estimated markers is worse), the
    mean of both otherwise (eq. 4.29); NaN rows for joints the body cannot use."""
    out = np.full((len(body.joints), 3), np.nan)
    if not len(body.joint_segments):
        return out
    r, t, known = poses
    seg = body.joint_segments  # (J, 2)
    ends = (r[seg] @ body.joint_offsets[..., None])[..., 0] + t[seg]  # (J, 2, 3)
    full = (np.append(flags == CASE_OBSERVED, False)[body.idx] | ~body.slot).all(axis=1)[seg]
    weight = known[seg] * np.where(full.any(axis=1, keepdims=True), full, True)
    total = weight.sum(axis=1)
    centre = np.einsum("jk,jki->ji", weight, ends) / np.maximum(total, 1)[:, None]
    out[body.joint_usable] = np.where(total[:, None] > 0, centre, np.nan)
    return out


def same_segments(a: Body, b: Body) -> bool:
    """Whether two bodies have the same segments, markers and shapes (their poses in a frame are the same)."""
    return len(a.members) == len(b.members) and all(
        np.array_equal(ma, mb) and np.array_equal(oa, ob)
        for ma, mb, oa, ob in zip(a.members, b.members, a.offsets, b.offsets, strict=True))
