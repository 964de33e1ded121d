"""The body model learned online from the frames seen so far, for whatever a given skeleton leaves open."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.sparse.csgraph import minimum_spanning_tree

from mocapflow.mocap.clustering import SegmentTracker, segment_names
from mocapflow.mocap.cor import SequentialCoR
from mocapflow.mocap.filling.body import Body
from mocapflow.mocap.filling.config import FillerConfig
from mocapflow.mocap.flags import CASE_OBSERVED
from mocapflow.mocap.model import Joint, Segment, SkeletonModel
from mocapflow.mocap.rigidfit import fit_one


def is_complete(skeleton: SkeletonModel) -> bool:
    """True when every segment has marker offsets and every joint both offsets: nothing is left to learn."""
    return all(seg.marker_offsets is not None for seg in skeleton.segments) and all(
        j.parent_offset is not None and j.child_offset is not None for j in skeleton.joints)


class SkeletonLearner:
    """The body model learned online from the frames seen so far, for whatever a given skeleton leaves open.

    - Segments: markers whose mutual distances keep a small spread (``clustering.SegmentTracker`` on a sample of the
      frames), unless the skeleton gives them.
    - Marker offsets: the segment's markers in the first frame showing three of them (both of a pair), centred on
      their centroid (the reference frame of Aristidou 4.4); a marker not seen then is added when first seen with
      three known ones. Unless given.
    - Joints: for every two segments, the closed-form centre of rotation (``cor.SequentialCoR``, Aristidou 4.4) fed
      with the poses of the frames allowed by ``update_joint_offsets``; the joints kept are the minimum spanning
      forest of the fit residuals among the pairs that turned enough relative to each other, hinges where the
      relative rotations keep to one axis (``CoREstimate.is_hinge``). A skeleton's own joints
      keep their pairs and, when given, their offsets.
    """

    def __init__(self, labels: list[str], rate: float, config: FillerConfig, given: SkeletonModel | None) -> None:
        self.labels = labels
        self.config = config
        self.tick = max(1, round(config.regroup_s * rate))
        self.min_frames = round(config.min_joint_s * rate / config.learn_stride)  # sampled frames
        self.min_spread = np.radians(config.min_joint_rotation_deg)
        index = {label: i for i, label in enumerate(labels)}
        self.tracker: SegmentTracker | None = None
        self.groups: list[tuple[int, ...]] = []
        self.names: dict[tuple[int, ...], str] = {}
        self.offsets: dict[tuple[int, ...], np.ndarray] = {}
        self.given_joints: list[Joint] | None = None
        if given is not None and given.segments:
            for seg in given.segments:
                group = tuple(index[m] for m in seg.markers if m in index)
                if not group:
                    continue
                self.groups.append(group)
                self.names[group] = seg.name
                if seg.marker_offsets is not None:
                    keep = [k for k, m in enumerate(seg.markers) if m in index]
                    self.offsets[group] = np.array([seg.marker_offsets[k] for k in keep], dtype=float)
            self.given_joints = list(given.joints) if given.joints else None
        else:
            stride = config.learn_stride
            options: dict[str, Any] = (
                {"threshold_mm": config.rigid_tolerance} if config.cluster_method == "distance-threshold" else {})
            self.tracker = SegmentTracker(
                labels, window=max(2, round(config.learn_window_s * rate / stride)),
                warmup=max(1, round(config.learn_warmup_s * rate / stride)),
                every=max(1, round(config.regroup_s * rate / stride)), method=config.cluster_method, **options)
        self.growing = {g for g in self.groups if len(g) >= 2 and g not in self.offsets}  # shapes still incomplete
        self.cors: dict[tuple[tuple[int, ...], tuple[int, ...]], SequentialCoR] = {}
        self.poses: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # per sample: R, t, usable; body order
        self.batches: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # the samples of each tick, stacked
        self.fed: dict[tuple[int, int], int] = {}  # per segment pair: batches already fed to its estimator
        self.queue: list[tuple[int, int]] = []  # pairs still to update in this round, a few per frame
        self.per_frame = 1
        self.found: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, float, bool]] = {}  # offsets, residual,
        # hinge
        self.body_groups: list[tuple[int, ...]] = []
        self.joints: list[Joint] = [j for j in self.given_joints or [] if j.parent_offset is not None
                                    and j.child_offset is not None]
        self.frame = 0

    def observe(self, observed: np.ndarray, seen: np.ndarray, flags: np.ndarray, body: Body | None,
                poses: Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray]]) -> SkeletonModel | None:
        """Take one frame (observed positions, the filled frame's flags, and a way to get the body's poses, read on
        sampled frames only); returns a new model when the learned one changed."""
        self.frame += 1
        changed = False
        if self.tracker is not None and self.frame % self.config.learn_stride == 0:
            segments = self.tracker.update(np.where(seen[:, None], observed, np.nan))
            if segments is not None:
                index = {label: i for i, label in enumerate(self.labels)}
                groups = [tuple(index[m] for m in seg.markers) for seg in segments.segments]
                names = segment_names(groups, self.labels)
                self.groups = groups
                self.names = dict(zip(groups, names, strict=True))
                self.offsets = {g: o for g, o in self.offsets.items() if g in self.names}
                self.growing = {g for g in groups if len(g) >= 2 and not np.isfinite(self.offsets.get(g, np.nan)).all()}
                self.cors = {k: c for k, c in self.cors.items() if k[0] in self.names and k[1] in self.names}
                changed = True
        for group in [g for g in self.growing if self._learn_offsets(g, observed, seen)]:
            changed = True
            if np.isfinite(self.offsets[group]).all():
                self.growing.remove(group)
        if body is not None and self.body_groups and self.frame % self.config.learn_stride == 0:
            r, t, known = poses()
            self.poses.append((r, t, known & self._usable(body, flags)))
        if changed:  # samples and pairs are in the old body's segment order
            self.poses.clear()
            self.batches.clear()
            self.fed.clear()
            self.queue.clear()
            return self._model()
        if self.frame % self.tick == 0 and self.poses:
            self.batches.append(tuple(np.stack(x) for x in zip(*self.poses, strict=True)))  # type: ignore[arg-type]
            self.poses.clear()
            if not self.queue:
                self.queue, self.found = self._pairs(), {}
                self.per_frame = max(1, -(-2 * len(self.queue) // self.tick))  # a round within half a tick
        if self.queue:  # spread over frames, so no single frame pays for every pair
            for pair in self.queue[: self.per_frame]:
                self._update_pair(*pair)
            del self.queue[: self.per_frame]
            if not self.queue:
                done = min(self.fed.values(), default=0)
                self.batches = self.batches[done:]
                self.fed = {pair: n - done for pair, n in self.fed.items()}
                joints = self._select_joints()
                if joints != self.joints:
                    self.joints = joints
                    return self._model()
        return None

    def _learn_offsets(self, group: tuple[int, ...], observed: np.ndarray, seen: np.ndarray) -> bool:
        """Start a segment's shape from the first frame showing three of its markers (both of a pair), centred on
        their centroid, and add each other marker when first seen with three known ones; True when it grew."""
        members = np.array(group)
        vis = seen[members]
        offsets = self.offsets.get(group)
        if offsets is None:
            if vis.sum() < min(3, len(group)):
                return False
            offsets = np.full((len(group), 3), np.nan)
            offsets[vis] = observed[members[vis]] - observed[members[vis]].mean(axis=0)
            self.offsets[group] = offsets
            return True
        known = np.isfinite(offsets[:, 0])
        new = vis & ~known
        if not new.any() or (vis & known).sum() < 3:
            return False
        use = vis & known
        fit = fit_one(offsets[use], observed[members[use]], np.ones(int(use.sum())))
        if fit is None:
            return False
        offsets[new] = (observed[members[new]] - fit[1]) @ fit[0]  # R^T (x - t)
        return True

    def _usable(self, body: Body, flags: np.ndarray) -> np.ndarray:
        """Segments whose pose this frame may update joint offsets (``update_joint_offsets``, tables 6.1-6.3)."""
        rule = self.config.update_joint_offsets
        observed = np.append(flags == CASE_OBSERVED, False)[body.idx]
        if rule == "observed":
            return (observed | ~body.slot).all(axis=1)
        if rule == "partial":
            return observed.any(axis=1)
        return np.ones(len(body.members), dtype=bool)

    def _pairs(self) -> list[tuple[int, int]]:
        """Segment pairs (body order) whose centre of rotation is estimated: the skeleton's joints still without
        offsets, or, with no joints given, every two segments with three or more markers."""
        groups = self.body_groups
        if self.given_joints is not None:
            by_name = {self.names[g]: k for k, g in enumerate(groups)}
            return [(by_name[j.parent], by_name[j.child]) for j in self.given_joints if j.parent in by_name
                    and j.child in by_name and (j.parent_offset is None or j.child_offset is None)]
        return [(a, b) for a in range(len(groups)) for b in range(a + 1, len(groups))
                if len(groups[a]) >= 3 and len(groups[b]) >= 3]

    def _update_pair(self, a: int, b: int) -> None:
        """Feed a pair's estimator the batches it has not seen; keep its centre if it is trustworthy yet."""
        cor = self.cors.setdefault((self.body_groups[a], self.body_groups[b]), SequentialCoR())
        for r, t, usable in self.batches[self.fed.get((a, b), 0):]:
            use = usable[:, a] & usable[:, b]
            if use.any():
                cor.update(r[use, a], t[use, a], r[use, b], t[use, b])
        self.fed[a, b] = len(self.batches)
        if cor.m < self.min_frames:
            return
        spread = np.linalg.eigvalsh(cor.m * np.eye(3) - cor.s.T @ cor.s / cor.m)[-1] / cor.m
        if spread < self.min_spread**2:
            return  # they turned too little relative to each other: any point fits
        est = cor.estimate()
        self.found[a, b] = (est.parent_offset, est.child_offset, est.residual, est.is_hinge)

    def _select_joints(self) -> list[Joint]:
        """The joints of this round: the given pairs, or the minimum spanning forest of the fit residuals."""
        groups = self.body_groups
        found = self.found
        if self.given_joints is None:
            costs = np.zeros((len(groups), len(groups)))
            for (a, b), (_, _, residual, _) in found.items():
                costs[a, b] = residual + 1e-9  # csgraph reads 0 as no edge
            tree = minimum_spanning_tree(costs).tocoo()
            kept = {(int(a), int(b)) for a, b in zip(tree.row, tree.col, strict=True)}
            found = {pair: estimate for pair, estimate in found.items() if pair in kept}
        given = {(j.parent, j.child): j for j in self.given_joints or []}
        joints = [j for j in self.given_joints or [] if j.parent_offset is not None and j.child_offset is not None]
        for (a, b), (pa, ch, _, hinge) in sorted(found.items()):
            parent, child = self.names[groups[a]], self.names[groups[b]]
            known = given.get((parent, child))
            joints.append(Joint(name=known.name if known else f"{parent}-{child}", parent=parent, child=child,
                                kind=known.kind if known else "hinge" if hinge else "ball", parent_offset=as_vector(pa),
                                child_offset=as_vector(ch)))
        return joints

    def _model(self) -> SkeletonModel:
        """The current model: segments with known offsets, and the joints found so far."""
        known = {g: np.isfinite(self.offsets[g][:, 0]) for g in self.groups if g in self.offsets}
        ready = [g for g in self.groups if g in known and known[g].sum() >= 2]
        self.body_groups = ready
        segments = [Segment(name=self.names[g], markers=[self.labels[m] for m, k in zip(g, known[g], strict=True) if k],
                            marker_offsets=[as_vector(o) for o in self.offsets[g][known[g]]]) for g in ready]
        names = {seg.name for seg in segments}
        joints = [j for j in self.joints if j.parent in names and j.child in names]
        return SkeletonModel(name="learned", segments=segments, joints=joints,
                             root=segments[0].name if segments else "")


def as_vector(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))

