"""Skeleton generation with no model given: labelled trajectories in, a parameterised ``SkeletonModel`` out.

The batch pipeline of Schoenauer (2007, chapter 3) with Aristidou's (2008) closed-form centres of rotation:

1. segments: markers grouped by the spread of their mutual distances (``clustering``; by default, rigidity at the
   recording's own noise level), without the distances of the odd wrong sample (``pair_statistics``);
2. joint costs for every pair of segments, on frames sampled every half second with a small jitter (Kirk et al.):
   the distance-variance cost of 3.5 (``joint_method="variance"``) or the residual of the closed-form centre of
   rotation of Aristidou 4.4 (``"closed-form"``); when some segments have only two markers (markers on the joints
   took the others), the spread of the most rigid pair of markers across the two segments (``closest_spreads``),
   scaled up where the two fix their orientations and their closed-form centre lies farther apart than a joint's;
3. topology: the minimum spanning tree of those costs, rooted at the most connected segment (3.7.7);
4. joint centres of the tree's joints, frame by frame; with segments of two markers, sequentially from an oriented
   root down (closed form between posed segments, sphere centres into a two-marker segment, which its joint then
   poses);
5. rigid parameters: marker and joint offsets averaged over many frames with outlier rejection (3.8.1);
6. hinges: joints the data locate only up to an axis (an exact hinge, or a knee whose other rotations are too
   small for its skin artefact), reported with their axis and placed on it level with the neighbouring joints;
7. honesty: every joint carries how far its centre could be off along its weakest direction
   (``CoREstimate.axial_uncertainty``) and whether that is small enough to call it located (``LOCATED_MM``), with the
   spread of the relative rotations about their principal axes, which says what motion a trial lacked.

The default joint estimator is the closed form: it is as accurate as the variance cost on simulated rigs, two to
three times faster, and much closer to the clinical knee centres on real skin markers (see
docs/skeleton-generation.md).

A bad part never costs the whole skeleton: a marker seen too rarely, a segment of one marker, a segment no frame
places or a joint too still to locate is logged on one warning line naming it, and the rest is kept. Errors a user
can act on raise ``CalibrationError``: too few frames, fewer than two segments, a joint method that cannot apply.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Literal

import numpy as np
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

from mocapflow.errors import CalibrationError
from mocapflow.mocap.clustering import (
    bodies,
    distance_spread,
    noise_floor,
    pair_statistics,
    partition,
    segment_names,
)
from mocapflow.mocap.cor import CoREstimate, joint_sides, joint_track, side_mean
from mocapflow.mocap.joints import (
    ALPHA,
    distance_stats,
    fit_joint_variance,
    marker_centroid,
    place_on_axis,
    spanning_tree,
)
from mocapflow.mocap.model import Joint, Segment, SkeletonModel
from mocapflow.mocap.report import Progress, steps
from mocapflow.mocap.rigid import fit_shape
from mocapflow.mocap.rigidfit import PoseFit
from mocapflow.mocap.sequential import MIN_TOGETHER, closed_form, sequential_tracks

log = logging.getLogger(__name__)

MIN_FRAMES = 50
"""Fewest frames a calibration accepts."""
MIN_VISIBLE = 0.1
"""A marker seen in a smaller fraction of the frames is left out of the model."""
PAIR_S = 0.5
"""Least time two markers must be seen together for their distance spread to say whether they are rigid: over a
shorter stretch any two markers look rigid."""
UNLABELLED_MM = 30.0
"""A recording whose markers' spread to their most rigid partner is typically larger than this (far beyond any skin
artefact) holds no rigid segment: its labels do not follow the markers."""
MIN_ROTATION_DEG = 2.0
"""Least RMS rotation between two joined segments for their joint to be located."""
APART_MM = 50.0
"""RMS distance (mm) between two segments' centre of rotation as each places it (the closed form's residual) beyond
which they hold no joint: skin moves markers by a couple of centimetres (the real captures' joints: 27 mm at most). In
a tree built from the closest markers' spreads, a pair farther apart has its spread scaled up by that ratio."""
LOCATED_MM = 20.0
"""Largest uncertainty (mm) along its weakest direction of a joint reported as located: functional methods reach
10-20 mm from a range-of-motion trial; gait alone leaves a hip uncertain by over 100 mm along its flexion axis."""
UNBOUNDED_MM = 10000.0
"""The uncertainty written for a joint whose data do not bound its centre at all (an exact hinge, a joint too still
to locate)."""
CANDIDATES = 3
"""With the variance cost, each segment's joint is optimised towards this many most likely partners (the cheapest
at the start); other pairs keep their cost at the start, an upper bound, which is far above any real joint's."""

JointMethod = Literal["auto", "variance", "closed-form"]


def pair_frames(rate: float) -> int:
    """Frames two markers must share for their distance spread to count (``PAIR_S`` seconds, at least 10)."""
    return max(10, round(PAIR_S * rate))


def sample_frames(frames: int, rate: float, every_s: float = 0.5, jitter_s: float = 1 / 30, at_least: int = 40,
                  at_most: int = 120, seed: int = 0) -> np.ndarray:
    """Sorted frame indices about every ``every_s`` seconds with a random jitter of up to ``jitter_s`` (Kirk et
    al.'s sampling, which keeps periodic errors from lining up), between ``at_least`` and ``at_most`` of them."""
    count = int(np.clip(round(frames / max(every_s * rate, 1.0)), min(at_least, frames), min(at_most, frames)))
    base = np.linspace(0, frames - 1, count)
    jitter = np.random.default_rng(seed).uniform(-1, 1, count) * jitter_s * rate
    return np.unique(np.clip(np.round(base + jitter), 0, frames - 1).astype(int))


def calibrate(positions: np.ndarray, labels: Sequence[str], rate: float, segments: int | None = None,
              method: Literal["rigidity", "spectral", "distance-threshold"] = "rigidity",
              joint_method: JointMethod = "auto", *, hinge_placement: Literal["neighbours", "estimator"] =
              "neighbours", name: str = "skeleton", progress: Progress | None = None, **cluster_options: object,
              ) -> SkeletonModel:
    """Segments, topology, joints and rigid parameters of an articulated body from (F, N, 3) labelled trajectories.

    ``segments`` fixes the number of segments (else the clusterer decides); ``method`` picks the clusterer and
    ``cluster_options`` go to it (``neighbour``, ``threshold_mm``...); ``joint_method`` picks the joint estimator.
    """
    positions, usable = _clean(positions, labels)
    stats = pair_statistics(positions[:, usable])
    spread = stats.spread(pair_frames(rate))
    if noise_floor(spread) > UNLABELLED_MM:
        raise CalibrationError(f"the markers keep their distances to no other marker (typical spread "
                               f"{noise_floor(spread):.0f} mm): the file looks unlabelled, its points changing "
                               "identity from frame to frame; label it first (mocapflow label)")
    groups = partition(method, stats, segments, pair_frames(rate), **cluster_options)
    groups = [[int(usable[i]) for i in group] for group in groups]
    return build_skeleton(positions, labels, rate, groups, joint_method, hinge_placement=hinge_placement, name=name,
                          progress=progress)


def _clean(positions: np.ndarray, labels: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Positions as float64 with NaN gaps, and the indices of markers seen often enough to use."""
    positions = np.array(positions, dtype=np.float64)
    if positions.ndim != 3 or positions.shape[2] != 3 or positions.shape[1] != len(labels):
        raise ValueError(f"positions must be (frames, {len(labels)}, 3), got {positions.shape}")
    if positions.shape[0] < MIN_FRAMES:
        raise CalibrationError(f"{positions.shape[0]} frames: calibration needs at least {MIN_FRAMES} frames of "
                               "varied motion")
    positions[~np.isfinite(positions).all(-1) | (positions == 0).all(-1)] = np.nan
    seen = np.isfinite(positions).all(-1).mean(0)
    usable = np.flatnonzero(seen >= MIN_VISIBLE)
    if len(usable) < 2:
        raise CalibrationError("fewer than two markers are visible often enough to calibrate")
    return positions, usable


def build_skeleton(positions: np.ndarray, labels: Sequence[str], rate: float, groups: Sequence[Sequence[int]],
                   joint_method: JointMethod = "auto", *,
                   hinge_placement: Literal["neighbours", "estimator"] = "neighbours", name: str = "skeleton",
                   progress: Progress | None = None) -> SkeletonModel:
    """Topology, joints and rigid parameters for a given partition of the markers (indices per segment)."""
    if joint_method not in ("auto", "variance", "closed-form"):
        raise ValueError(f"unknown joint method {joint_method!r}; choose auto, variance or closed-form")
    positions, usable = _clean(positions, labels)
    kept = set(usable.tolist())  # the rare markers are left out
    if len(kept) < len(labels):
        log.warning("left out markers seen in under %d %% of the frames: %s", round(100 * MIN_VISIBLE),
                    ", ".join(label for i, label in enumerate(labels) if i not in kept))
    groups = [g for g in ([m for m in group if m in kept] for group in groups) if g]
    return _build(positions, labels, rate, groups, joint_method, hinge_placement, name, progress)


def _build(positions: np.ndarray, labels: Sequence[str], rate: float, groups: Sequence[Sequence[int]],
           joint_method: JointMethod, hinge_placement: Literal["neighbours", "estimator"], name: str,
           progress: Progress | None) -> SkeletonModel:
    """``build_skeleton`` on cleaned positions (``_clean``) and groups of usable markers; it starts again without the
    segments it has to leave out."""
    requested = joint_method
    frames = positions.shape[0]
    for group in groups:
        if len(group) < 2:
            log.warning("left out %s: the only marker of its segment (a segment needs at least 2)",
                        ", ".join(labels[m] for m in group))
    groups = [list(g) for g in groups if len(g) >= 2]
    if len(groups) < 2:
        raise CalibrationError("fewer than two segments of two markers or more: there is no joint to find")
    names = segment_names(groups, labels)
    reference = int(np.argmax(np.isfinite(positions).all(-1).sum(1)))
    poses = [_marker_poses(positions[:, g], reference) for g in groups]
    flat = [seg for seg, pose in zip(names, poses, strict=True) if pose is None]
    if joint_method == "closed-form" and flat:
        raise CalibrationError(f"segments {', '.join(flat)} have fewer than 3 markers: the closed-form centre of "
                               "rotation needs each segment's orientation; use the variance joint method "
                               "(--joints variance)")
    sequential = joint_method == "auto" and bool(flat) and any(pose is not None for pose in poses)
    spread = distance_spread(positions, pair_frames(rate))
    if sequential:
        # the closed form needs every segment's orientation: segments of two markers (markers on the joints took
        # the others) are joined where their closest markers keep their distance best, and their joints are
        # found down the tree from the segments whose markers fix their orientation
        log.info("segments %s have fewer than 3 markers: the tree joins the segments whose closest markers keep "
                 "their distance best, unless their centre of rotation lies too far apart for a joint; joints found "
                 "down the tree", ", ".join(flat))
        costs = closest_spreads(spread, groups)
        # but two segments whose markers fix their orientations, and whose centre of rotation as each places it lies
        # farther apart than a joint's (their closest markers may keep their distance by chance: a shank's and the
        # other thigh's over a stride), have that spread scaled up by how many times farther
        fitted = _pair_costs(positions, groups, poses, sample_frames(frames, rate), "closed-form", progress)
        costs = costs * np.maximum(1.0, np.where(np.isfinite(fitted), fitted, 0.0) / APART_MM)
    else:
        if joint_method == "auto" and flat:
            log.info("no segment has 3 markers: joints by the distance-variance cost")
        joint_method = ("variance" if flat else "closed-form") if joint_method == "auto" else joint_method
        costs = _pair_costs(positions, groups, poses, sample_frames(frames, rate), joint_method, progress)
    # a joint joins segments of one body: not two subjects captured together, nor a subject and a prop
    body = bodies(spread)
    own = np.array([np.bincount(body[g]).argmax() for g in groups])
    costs = np.where(own[:, None] == own[None, :], costs, np.inf)
    parts, part = connected_components(np.isfinite(costs) & ~np.eye(len(groups), dtype=bool), directed=False)
    if parts > 1:  # keep the body that holds the most markers
        kept = max(range(parts), key=lambda c: sum(len(g) for g, p in zip(groups, part, strict=True) if p == c))
        main = [m for g, p in zip(groups, part, strict=True) if p == kept for m in g]
        left = [g for g, p in zip(groups, part, strict=True) if p != kept]
        apart = [m for g in left if np.isfinite(spread[np.ix_(g, main)]).any() for m in g]  # seen, moving apart
        if apart:
            log.warning("left out %d markers that move on their own, apart from the body calibrated (another subject "
                        "or a prop): %s; calibrate each subject alone (--markers GLOB)", len(apart),
                        ", ".join(labels[m] for m in apart))
        for g in left:
            if g[0] not in apart:
                log.warning("left out %s: never seen long enough together with the rest of the body to join it",
                            ", ".join(labels[m] for m in g))
        return _build(positions, labels, rate, [g for g, p in zip(groups, part, strict=True) if p == kept],
                      requested, hinge_placement, name, progress)
    root, edges = spanning_tree(costs)

    fixed: set[tuple[int, int]] = set()  # joints too still to locate, placed between the closest markers
    chosen = np.union1d(sample_frames(frames, rate, every_s=0.05, at_least=200, at_most=600, seed=1), [reference])
    ref = int(np.searchsorted(chosen, reference))
    if sequential:
        root, edges = _root_oriented(root, edges, poses)
        tracks = sequential_tracks(positions[chosen], groups, [p and p.subset(chosen) for p in poses], edges, ref,
                                    progress)
    else:
        tracks = {}
        for parent, child in steps(edges, len(edges), "joints", progress):
            start = _start_track(positions, groups, poses, parent, child, chosen)
            if joint_method == "variance":
                markers = positions[chosen][:, list(groups[parent]) + list(groups[child])]
                start = fit_joint_variance(markers, start, max_iterations=30).centres
            tracks[parent, child] = start

    for attempt in range(2):
        shapes, offsets = [], {}
        for s, group in enumerate(groups):
            attached = [e for e in edges if s in e]
            extras = np.stack([tracks[e] for e in attached], 1) if attached else None
            try:
                shape = fit_shape(positions[chosen][:, group], extras, reference=ref)
            except ValueError as exc:
                log.warning("left out %s (segment %s): %s", ", ".join(labels[m] for m in group), names[s], exc)
                return _build(positions, labels, rate, [g for g in groups if g is not group], requested,
                              hinge_placement, name, progress)
            shapes.append(shape)
            offsets.update({(s, e): shape.extra_offsets[j] for j, e in enumerate(attached)})
        # deg, deg, mean rotation (deg), estimate
        motion = {e: _relative_motion(shapes[e[0]].pose, shapes[e[1]].pose) for e in edges}
        still = [e for e in edges if motion[e][0] < MIN_ROTATION_DEG and e not in fixed]
        if not still or attempt:
            break
        for parent, child in still:  # no centre of rotation to find: the joint goes between the closest markers
            log.warning("joint %s-%s: the segments turned only %.1f deg RMS relative to each other (a joint is "
                        "located from %g); placed between their closest markers: record more varied motion to "
                        "locate it", names[parent], names[child], motion[parent, child][0], MIN_ROTATION_DEG)
            tracks[parent, child] = _closest_track(positions[chosen], groups[parent], groups[child])
        fixed |= set(still)
    estimates = {e: est for e, (*_, est) in motion.items() if est is not None}
    # a hinge needs both segments' orientations (a segment of two markers is posed through its joints, unless they
    # all lie on a line)
    oriented = {e for e in edges if not (shapes[e[0]].in_line or shapes[e[1]].in_line) and e not in fixed
                and e in estimates}
    located = [e for e in oriented if not estimates[e].is_hinge]  # joints whose data fix a point
    joints = []
    for parent, child in edges:
        est = estimates.get((parent, child))
        around = [e for e in located if e != (parent, child)]
        p_near, c_near = [e for e in around if parent in e], [e for e in around if child in e]
        hinge = est is not None and (parent, child) in oriented and (est.is_hinge or bool(
            p_near and c_near and _level_fits(est, [_offset(estimates[e], e, parent) for e in p_near],
                                              [_offset(estimates[e], e, child) for e in c_near])))
        p_off, c_off = offsets[parent, (parent, child)], offsets[child, (parent, child)]
        posture = motion[parent, child][2]
        axis = est.axis if hinge and est is not None else None
        if est is not None and hinge and hinge_placement == "neighbours":
            p_off, c_off = place_on_axis(p_off, c_off, est.axis, est.child_axis, [offsets[parent, e] for e in p_near],
                                         [offsets[child, e] for e in c_near])
        pp, pc = shapes[parent].pose, shapes[child].pose
        sides = joint_sides(pp.rotation_matrices, pp.translations, pc.rotation_matrices, pc.translations, p_off, c_off)
        track = side_mean(sides)
        apart = np.linalg.norm(sides[0] - sides[1], axis=1)
        _, mean, sd = distance_stats(track, positions[chosen][:, list(groups[parent]) + list(groups[child])], ALPHA)
        uncertainty = UNBOUNDED_MM if est is None or (parent, child) in fixed else min(
            float(est.axial_uncertainty), UNBOUNDED_MM)
        joints.append(Joint(
            name=f"{names[parent]}-{names[child]}", parent=names[parent], child=names[child],
            kind="hinge" if hinge else "ball", parent_offset=_vec(p_off), child_offset=_vec(c_off),
            axis=_vec(axis) if axis is not None else None, cost=float(costs[parent, child]), distance_mean=mean,
            distance_sd=sd, gap_mm=_rms(apart), rotation_deg=float(motion[parent, child][0]),
            uncertainty_mm=uncertainty, located=uncertainty <= LOCATED_MM,
            motion_sd_deg=_vec(motion[parent, child][1]), posture=_vec(posture) if posture is not None else None))
    spread = distance_spread(positions, pair_frames(rate))
    segments_out = [Segment(name=names[s], markers=[labels[m] for m in g],
                            marker_offsets=[_vec(o) for o in shapes[s].marker_offsets],
                            marker_spread_mm=[round(float(x), 2) for x in shapes[s].marker_spread],
                            rigidity_mm=float(np.nanmean(spread[np.ix_(g, g)][np.triu_indices(len(g), 1)])))
                    for s, g in enumerate(groups)]
    return SkeletonModel(name=name, segments=segments_out, joints=joints, root=names[root])


def _rms(values: np.ndarray) -> float | None:
    """Root mean square of the finite values (2 decimals), None when there are none."""
    finite = values[np.isfinite(values)]
    return round(float(np.sqrt(np.mean(finite**2))), 2) if len(finite) else None


def closest_spreads(spread: np.ndarray, groups: Sequence[Sequence[int]]) -> np.ndarray:
    """(S, S) spread of the most rigid pair of markers across every two segments: small across a joint, whose
    nearby markers keep their distances, large across segments that move freely of each other."""
    d = np.where(np.isfinite(spread), spread, np.inf)
    costs = np.full((len(groups), len(groups)), np.inf)
    for a, ga in enumerate(groups):
        for b in range(a + 1, len(groups)):
            costs[a, b] = costs[b, a] = d[np.ix_(ga, groups[b])].min()
    return costs


def _closest_track(positions: np.ndarray, a: Sequence[int], b: Sequence[int]) -> np.ndarray:
    """(F, 3) midpoint of the two markers, one of each segment, that are closest on average."""
    ma, mb = positions[:, list(a)], positions[:, list(b)]
    d = np.linalg.norm(ma[:, :, None] - mb[:, None], axis=-1)
    count = np.isfinite(d).sum(axis=0)  # pairs never seen together are not chosen (unless no pair ever is)
    gap = np.where(count > 0, np.nansum(d, axis=0) / np.maximum(count, 1), np.inf)
    i, j = np.unravel_index(np.argmin(gap), gap.shape)
    return (ma[:, i] + mb[:, j]) / 2


def _root_oriented(root: int, edges: list[tuple[int, int]], poses: Sequence[PoseFit | None]
                   ) -> tuple[int, list[tuple[int, int]]]:
    """The tree rooted at a segment whose markers fix its orientation (the given root if they do, else the one
    with the most joints), edges parents first."""
    if poses[root] is None:
        degree = np.bincount(np.ravel(edges), minlength=len(poses))
        root = max((s for s, p in enumerate(poses) if p is not None), key=lambda s: (degree[s], -s))
    near: dict[int, list[int]] = {}
    for a, b in edges:
        near.setdefault(a, []).append(b)
        near.setdefault(b, []).append(a)
    order, out = [root], []
    for s in order:
        for t in near.get(s, []):
            if t not in order:
                order.append(t)
                out.append((s, t))
    return root, out


def _vec(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


def _marker_poses(markers: np.ndarray, reference: int) -> PoseFit | None:
    """Poses of a segment from its markers alone (all frames), or None when they cannot fix its orientation."""
    if markers.shape[1] < 3:
        return None
    try:
        return fit_shape(markers, reference=reference).pose
    except ValueError:
        return None


def _start_track(positions: np.ndarray, groups: Sequence[Sequence[int]], poses: Sequence[PoseFit | None], a: int,
                 b: int, frames: np.ndarray) -> np.ndarray:
    """Initial joint centres on ``frames``: the closed-form centre of rotation (from all frames) when both
    orientations are known, else the centroid of both segments' markers (Schoenauer's start)."""
    pa, pb = poses[a], poses[b]
    if pa is None or pb is None:
        return marker_centroid(positions[frames][:, list(groups[a]) + list(groups[b])])
    est = closed_form(pa, pb)
    return joint_track(pa.rotation_matrices[frames], pa.translations[frames], pb.rotation_matrices[frames],
                       pb.translations[frames], est.parent_offset, est.child_offset)


def _pair_costs(positions: np.ndarray, groups: Sequence[Sequence[int]], poses: Sequence[PoseFit | None],
                frames: np.ndarray, joint_method: JointMethod, progress: Progress | None) -> np.ndarray:
    """Symmetric joint-cost matrix of every segment pair (``frames``: where the variance cost is evaluated)."""
    n = len(groups)
    costs = np.full((n, n), np.inf)
    starts = {}
    all_pairs = [(a, b) for a in range(n) for b in range(a + 1, n)]
    for a, b in steps(all_pairs, len(all_pairs), "joint costs", progress):
        pa, pb = poses[a], poses[b]
        if joint_method == "closed-form":
            both = (np.isfinite(pa.rotations).all(1) & np.isfinite(pb.rotations).all(1) if pa is not None
                    and pb is not None else np.zeros(0, bool))
            cost = closed_form(pa, pb).residual if pa is not None and pb is not None and (
                both.sum() >= MIN_TOGETHER) else np.inf
        else:
            starts[a, b] = _start_track(positions, groups, poses, a, b, frames)
            both = poses[a] is not None and poses[b] is not None
            markers = positions[frames][:, list(groups[a]) + list(groups[b])]
            cost = distance_stats(starts[a, b], markers)[0] if both else np.inf
        costs[a, b] = costs[b, a] = cost
    if joint_method == "variance":
        shortlist = set()
        for s in range(n):
            partners = np.argsort(costs[s])[: CANDIDATES if poses[s] is not None else n]
            shortlist |= {(min(s, int(o)), max(s, int(o))) for o in partners if o != s}
        for a, b in steps(sorted(shortlist), len(shortlist), "joint optimisation", progress):
            markers = positions[frames][:, list(groups[a]) + list(groups[b])]
            costs[a, b] = costs[b, a] = fit_joint_variance(markers, starts[a, b], max_iterations=8).cost
    return costs


def _level_fits(est: CoREstimate, parent_neighbours: list[np.ndarray], child_neighbours: list[np.ndarray]) -> bool:
    """Whether the data cannot tell a joint's closed-form centre from the point of its weakest axis level with the
    neighbouring joints (offsets in the parent's and the child's frame): the two are closer along the axis than a
    misfit as large as the residual can move the centre (``CoREstimate.axial_uncertainty``)."""
    rule, _ = place_on_axis(est.parent_offset, est.child_offset, est.axis, est.child_axis, parent_neighbours,
                            child_neighbours)
    shift = abs(float(est.axis @ (rule - est.parent_offset)))
    log.debug("hinge ratio %.4f, level point %.1f mm along the axis, axial uncertainty %.1f mm", est.ratio, shift,
              est.axial_uncertainty)
    return shift <= est.axial_uncertainty


def _offset(est: CoREstimate, edge: tuple[int, int], segment: int) -> np.ndarray:
    """A closed-form centre in the frame of ``segment``, one of the two segments of ``edge``."""
    return est.parent_offset if segment == edge[0] else est.child_offset


def _relative_motion(parent: PoseFit,
                     child: PoseFit) -> tuple[float, np.ndarray, np.ndarray | None, CoREstimate | None]:
    """RMS angle (deg) of the child's rotation relative to the parent about its mean, its SDs (deg) about its three
    principal axes (largest first), the mean as a rotation vector (deg), and the closed-form centre of rotation with
    its hinge test (no mean and no centre without two frames where both poses are known)."""
    rp, rc = parent.rotation_matrices, child.rotation_matrices
    known = (np.isfinite(rp).all((1, 2)) & np.isfinite(rc).all((1, 2)) & np.isfinite(parent.translations).all(1)
             & np.isfinite(child.translations).all(1))
    if known.sum() < 2:
        return 0.0, np.zeros(3), None, None
    rel = Rotation.from_matrix(np.einsum("fba,fbc->fac", rp[known], rc[known]))
    mean = rel.mean()
    about = (mean.inv() * rel).as_rotvec()
    spread = float(np.degrees(np.sqrt(np.mean((about**2).sum(axis=1)))))
    sds = np.degrees(np.sqrt(np.maximum(np.linalg.eigvalsh(about.T @ about / len(about))[::-1], 0.0)))
    return spread, sds, np.degrees(mean.as_rotvec()), closed_form(parent, child)
