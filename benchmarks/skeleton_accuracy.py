"""Skeleton generation accuracy: both joint estimators on simulated rigs against their truth, on the real lower-body
file against clinical landmarks, the hinge placement rules side by side, and what the CMU files give.

Run: python benchmarks/skeleton_accuracy.py [--frames 2000]. Prints Markdown tables (the ones in
docs/skeleton-generation.md). Simulated rigs: 120 Hz, 0.5 mm noise, seed 0; errors are mean distances (mm) between
solved and true joint centres over all frames, per joint, then the mean and the max over the joints of a kind. Hinge
errors are also split along the hinge axis and across it. Times are CPU seconds on one core (BLAS threads pinned).

Real lower-body file: segments and tree against the expert's model; knee and ankle centres against the midpoints of
the medial and lateral markers (the clinical definitions), hips against the Harrington et al. (2007) regression from
the pelvis markers (itself about 5 mm per axis off MRI hip centres).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass

import _common
import numpy as np
from scipy.optimize import minimize_scalar

from mocapflow.io.markers import MarkerData, read_markers
from mocapflow.mocap.calibration import calibrate
from mocapflow.mocap.clustering import distance_spread, partition_threshold
from mocapflow.mocap.model import Joint, SkeletonModel
from mocapflow.mocap.rigid import bone_lengths
from mocapflow.mocap.rigidfit import quaternion_matrices
from mocapflow.mocap.rigs import make_rig
from mocapflow.mocap.simulator import SimRecording, SimulatorConfig, simulate
from mocapflow.mocap.solve import SkeletonPose, solve

LOWER_BODY = "lowerbody_clusters_knee_0401.c3d"
METHODS = ("closed-form", "variance")
CASES = [("human", {}), ("rods", {}), ("quadruped", {}), ("quadruped, first 28 markers", {}),
         ("human, 5 mm soft-tissue artefact", {"skin_mm": 5.0}),
         ("human, dropouts and 1-4 s gaps", {"dropout_rate": 0.5, "long_gaps": 4.0})]
EXPERT_LOWER_BODY = {  # segment -> markers, and the tree, as a gait lab's model has them
    "pelvis": ["LASI", "RASI", "LPSI", "RPSI"], "trunk": ["LSHL", "CLAV", "RSHL", "C7"],
    **{f"{s} thigh": [f"{s}TH{i}" for i in range(1, 5)] for s in "LR"},
    **{f"{s} shank": [f"{s}SH{i}" for i in range(1, 5)] + [f"{s}MKN", f"{s}LKN", f"{s}LAK", f"{s}MAK"] for s in "LR"},
    **{f"{s} foot": [f"{s}TOE", f"{s}MT5", f"{s}CAL", f"{s}CUN"] for s in "LR"},
}
EXPERT_LOWER_TREE = [("pelvis", "trunk")] + [pair for s in "LR" for pair in (
    ("pelvis", f"{s} thigh"), (f"{s} thigh", f"{s} shank"), (f"{s} shank", f"{s} foot"))]
EXPERT_CMU = {  # the CMU 41-marker set by bone; joint markers go with the bone they sit on (KNE femur, ANK fibula)
    "pelvis": ["LFWT", "RFWT", "LBWT", "RBWT"], "trunk": ["CLAV", "STRN", "C7", "T10", "RBAC", "LSHO", "RSHO"],
    "head": ["LFHD", "RFHD", "LBHD", "RBHD"],
    **{f"{s} thigh": [f"{s}THI", f"{s}KNE"] for s in "LR"}, **{f"{s} shank": [f"{s}SHN", f"{s}ANK"] for s in "LR"},
    **{f"{s} foot": [f"{s}HEE", f"{s}MT5", f"{s}TOE"] for s in "LR"},
    **{f"{s} upper arm": [f"{s}UPA", f"{s}ELB"] for s in "LR"},
    **{f"{s} forearm and hand": [f"{s}FRM", f"{s}WRA", f"{s}WRB", f"{s}FIN"] for s in "LR"},
}




def same_partition(skeleton: SkeletonModel, expected: list[list[str]]) -> bool:
    """Whether the skeleton's segments hold exactly the expected marker groups."""
    return sorted(sorted(s.markers) for s in skeleton.segments) == sorted(sorted(g) for g in expected)


def axis_split(pose: SkeletonPose, skeleton: SkeletonModel, j: int, reference: np.ndarray) -> tuple[float, float]:
    """Mean signed error along a hinge's axis (world, from the parent's pose) and mean error across it, mm."""
    joint = skeleton.joints[j]
    axis = np.einsum("fab,b->fa", quaternion_matrices(pose.rotations[:, pose.segment_names.index(joint.parent)]),
                     np.asarray(joint.axis))
    error = pose.joint_centres[:, j] - reference
    along = np.einsum("fa,fa->f", error, axis)
    return float(np.nanmean(along)), float(np.nanmean(np.linalg.norm(error - along[:, None] * axis, axis=1)))


@dataclass
class SimScore:
    groups: bool
    tree: bool
    kinds: bool
    ball: list[float]
    hinge: list[float]
    along: list[float]
    across: list[float]
    solve_s: float


def score_simulated(rec: SimRecording, rig: str, skeleton: SkeletonModel, labels: list[str]) -> SimScore:
    """Partition, tree and joint kinds against the truth, and the solved joint errors per kind (mm)."""
    of = dict(zip(rec.labels, rec.marker_segment, strict=True))
    present = {of[m] for m in labels}
    groups = same_partition(skeleton, [[m for m in labels if of[m] == s] for s in present])
    seg = {s.name: of[s.markers[0]] for s in skeleton.segments}
    truth = {frozenset(pc): k for k, pc in enumerate(zip(rec.joint_parent, rec.joint_child, strict=True))}
    edges = [frozenset((seg[j.parent], seg[j.child])) for j in skeleton.joints]
    tree = set(edges) == {e for e in truth if e <= present}
    true_kind = dict(zip(make_rig(rig).segments, make_rig(rig).joint_kinds, strict=True))
    index = [rec.labels.index(m) for m in labels]
    pose, solve_s = _common.timed(solve, skeleton, rec.positions[:, index], labels)
    out = SimScore(groups, tree, True, [], [], [], [], solve_s)
    for j, (joint, edge) in enumerate(zip(skeleton.joints, edges, strict=True)):
        if edge not in truth:
            continue
        k = truth[edge]
        out.kinds &= joint.kind == true_kind[rec.joint_child[k]]
        reference = rec.joint_centres[:, k]
        (out.ball if joint.kind == "ball" else out.hinge).append(
            float(np.nanmean(np.linalg.norm(pose.joint_centres[:, j] - reference, axis=1))))
        if joint.kind == "hinge":
            along, across = axis_split(pose, skeleton, j, reference)
            out.along.append(abs(along))
            out.across.append(across)
    return out


def _pair(values: list[float]) -> str:
    return f"{np.mean(values):.2f} / {np.max(values):.2f}" if values else "-"


def simulated(frames: int) -> None:
    """The simulated-rig table, both estimators, and the threshold clusterer's partitions."""
    print(f"## Simulated rigs ({frames} frames at 120 Hz, 0.5 mm noise)\n")
    print("| case | estimator | markers | segments | tree (kinds) | ball mean / max | hinge mean / max | "
          "hinge along / across axis | middle rod | calibrate s | solve s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    threshold = []
    for name, options in CASES:
        rig = name.split(",")[0]
        rec = simulate(SimulatorConfig(rig=rig, rate=120, noise_mm=0.5, seed=0, **options), frames)
        labels = rec.labels[:28] if "28" in name else rec.labels
        positions = rec.positions[:, : len(labels)]
        for method in METHODS:
            skeleton, seconds = _common.timed(calibrate, positions, labels, rec.rate, joint_method=method)
            s = score_simulated(rec, rig, skeleton, labels)
            rod = "-"
            if rig == "rods":
                length = next(iter(bone_lengths(skeleton).values()))
                rod = f"{length:.2f} mm ({100 * (length / 359 - 1):+.2f} %)"
            along = f"{np.mean(s.along):.2f} / {np.mean(s.across):.2f}" if s.along else "-"
            tree = f"{'exact' if s.tree else 'wrong'} ({'exact' if s.kinds else 'wrong'})"
            print(f"| {name} | {method} | {len(labels)} | {'exact' if s.groups else 'wrong'} | {tree} | "
                  f"{_pair(s.ball)} | {_pair(s.hinge)} | {along} | {rod} | {seconds:.2f} | {s.solve_s:.2f} |")
        of = dict(zip(rec.labels, rec.marker_segment, strict=True))
        groups = partition_threshold(distance_spread(positions))
        threshold.append(sorted(sorted(labels[i] for i in g) for g in groups)
                         == sorted(sorted(m for m in labels if of[m] == s) for s in {of[m] for m in labels}))
    print(f"\nThe distance-threshold clusterer's partition is exact on {sum(threshold)} of {len(threshold)} cases.")
    print("The true middle rod is 359 mm between its joints (the thesis measured 360.46 mm against 359 +- 1.5).")


@dataclass
class LowerBody:
    """The real lower-body recording and its clinical landmarks."""

    data: MarkerData

    def point(self, label: str) -> np.ndarray:
        """(F, 3) trajectory of a marker, NaN where missing (all-zero samples included)."""
        p = self.data.positions[:, self.data.labels.index(label)].astype(float)
        p[(p == 0).all(-1)] = np.nan
        return p

    def mid(self, a: str, b: str) -> np.ndarray:
        """(F, 3) midpoint of two markers."""
        return 0.5 * (self.point(a) + self.point(b))

    def landmarks(self) -> dict[str, np.ndarray]:
        """Clinical joint centres: knee and ankle marker midpoints, hips by Harrington et al. (2007)."""
        out = {}
        for side in "LR":
            out[f"{side} knee"] = self.mid(f"{side}MKN", f"{side}LKN")
            out[f"{side} ankle"] = self.mid(f"{side}LAK", f"{side}MAK")
        asis = self.mid("LASI", "RASI")
        width = np.linalg.norm(self.point("RASI") - self.point("LASI"), axis=1)
        depth = np.linalg.norm(asis - self.mid("LPSI", "RPSI"), axis=1)
        right = _unit(self.point("RASI") - self.point("LASI"))
        forward = asis - self.mid("LPSI", "RPSI")
        forward = _unit(forward - np.einsum("fa,fa->f", forward, right)[:, None] * right)
        up = np.cross(right, forward)
        for side, sign in (("L", -1.0), ("R", 1.0)):
            out[f"{side} hip"] = (asis + (-0.24 * depth - 9.9)[:, None] * forward
                                  + (-0.30 * width - 10.9)[:, None] * up + sign * (0.33 * width + 7.3)[:, None] * right)
        return out

    def joint_index(self, skeleton: SkeletonModel, name: str) -> int:
        """The calibrated joint standing for a landmark (the one whose child holds the distal segment's marker)."""
        side, kind = name.split()
        part = {m: s.name for s in skeleton.segments for m in s.markers}
        child = part[{"hip": f"{side}TH1", "knee": f"{side}SH1", "ankle": f"{side}TOE"}[kind]]
        parent = part[{"hip": "LASI", "knee": f"{side}TH1", "ankle": f"{side}SH1"}[kind]]
        return next(j for j, x in enumerate(skeleton.joints) if {x.parent, x.child} == {parent, child})


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def expert_tree(skeleton: SkeletonModel, expert: dict[str, list[str]],
                tree: list[tuple[str, str]]) -> bool:
    """Whether the skeleton's joints link the segments holding the expert tree's segments' markers, and no others."""
    part = {m: s.name for s in skeleton.segments for m in s.markers}
    expected = {frozenset((part[expert[a][0]], part[expert[b][0]])) for a, b in tree}
    return {frozenset((j.parent, j.child)) for j in skeleton.joints} == expected


def real_lower_body(skeletons: dict[str, SkeletonModel], times: dict[str, float], body: LowerBody) -> None:
    """The real lower-body table: segments and tree against the expert, joints against the clinical landmarks."""
    data = body.data
    print(f"\n## Real: {LOWER_BODY} ({data.n_frames} frames at {data.rate:g} Hz, {data.n_markers} markers)\n")
    print("Knees and ankles against the midpoints of the medial and lateral markers, hips against the Harrington "
          "regression; mean distance over frames, mm.\n")
    print("| estimator | segments | tree | left / right knee | knee along / across axis | left / right ankle | "
          "left / right hip | marker fit | calibrate s |")
    print("|---|---|---|---|---|---|---|---|---|")
    landmarks = body.landmarks()
    for method, skeleton in skeletons.items():
        pose = solve(skeleton, data.positions, data.labels)
        errors, along, across = {}, [], []
        for name, reference in landmarks.items():
            j = body.joint_index(skeleton, name)
            errors[name] = np.nanmean(np.linalg.norm(pose.joint_centres[:, j] - reference, axis=1))
            if name.endswith("knee") and skeleton.joints[j].kind == "hinge":
                a, c = axis_split(pose, skeleton, j, reference)
                along.append(abs(a))
                across.append(c)
        groups = same_partition(skeleton, list(EXPERT_LOWER_BODY.values()))
        tree = expert_tree(skeleton, EXPERT_LOWER_BODY, EXPERT_LOWER_TREE)
        split = f"{np.mean(along):.1f} / {np.mean(across):.1f}" if along else "not hinges"
        print(f"| {method} | {'expert' if groups else 'other'} | {'expert' if tree else 'other'} | "
              f"{errors['L knee']:.1f} / {errors['R knee']:.1f} | {split} | {errors['L ankle']:.1f} / "
              f"{errors['R ankle']:.1f} | {errors['L hip']:.1f} / {errors['R hip']:.1f} | "
              f"{np.nanmean(pose.residual):.2f} | {times[method]:.2f} |")


Rule = Callable[[np.ndarray, np.ndarray, float], float]


def _midplane(points: np.ndarray, radii: np.ndarray, origins: float) -> float:
    return origins


def _centroid(points: np.ndarray, radii: np.ndarray, origins: float) -> float:
    return float(points.mean())


def _nearest_two(points: np.ndarray, radii: np.ndarray, origins: float) -> float:
    return float(points[np.argsort(radii)[:2]].mean())


def _alpha(points: np.ndarray, radii: np.ndarray, origins: float) -> float:
    return float(minimize_scalar(lambda s: np.sqrt(radii ** 2 + (points - s) ** 2).sum(),
                                 bounds=(points.min(), points.max()), method="bounded").x)


RULES: dict[str, Rule] = {
    "mid-plane between the two segments' marker centroids (the closed form's minimum-norm point)": _midplane,
    "centroid of both segments' markers projected on the axis": _centroid,
    "midpoint of the two markers nearest the axis": _nearest_two,
    "alpha term of the variance cost along the axis only (least summed marker distance)": _alpha,
}
"""Other ways to choose a hinge's point on its axis, each from the axial coordinates and axis distances of both
segments' markers and the mean axial coordinate of the two segment origins (all relative to the calibrated point)."""


def rule_shifts(skeleton: SkeletonModel, pose: SkeletonPose, joint: Joint) -> dict[str, float]:
    """Where each alternative rule puts a hinge on its axis, as a shift (mm) from the calibrated point.

    Markers of both segments are taken to the parent's frame through the calibrated joint (the child's axis is
    the parent's, turned by the mean relative rotation), as axial coordinates and distances from the axis.
    """
    names = [s.name for s in skeleton.segments]
    axis = np.asarray(joint.axis)
    rp = quaternion_matrices(pose.rotations[:, names.index(joint.parent)])
    rc = quaternion_matrices(pose.rotations[:, names.index(joint.child)])
    relative = np.nanmean(np.einsum("fba,fbc->fac", rp, rc), axis=0)
    child_axis = _unit(relative.T @ axis)
    points, radii = [], []
    for segment, offset, direction in ((joint.parent, joint.parent_offset, axis),
                                       (joint.child, joint.child_offset, child_axis)):
        rel = np.asarray(skeleton.segments[names.index(segment)].marker_offsets) - np.asarray(offset)
        t = rel @ direction
        points.append(t)
        radii.append(np.linalg.norm(rel - t[:, None] * direction, axis=1))
    origins = 0.5 * (float(-np.asarray(joint.parent_offset) @ axis) - float(np.asarray(joint.child_offset)
                                                                            @ child_axis))
    pts, rad = np.concatenate(points), np.concatenate(radii)
    return {name: rule(pts, rad, origins) for name, rule in RULES.items()}


def hinge_rules(frames: int, lower_body: tuple[SkeletonModel, SkeletonModel, LowerBody] | None) -> None:
    """Along-axis error of every placement rule: simulated hinges against the truth, real knees against the
    marker midpoints (closed-form estimator)."""
    print("\n## Where a hinge sits on its axis\n")
    print("Mean absolute error along the hinge axis, mm (closed-form estimator; the across-axis error does not "
          "depend on the rule).\n")
    columns: dict[str, dict[str, list[float]]] = {}

    def add(column: str, skeleton: SkeletonModel, pose: SkeletonPose, own_pose: SkeletonPose,
            joints: list[tuple[int, np.ndarray]]) -> None:
        """``own_pose``: the same skeleton with every hinge left where the estimator put it."""
        for j, reference in joints:
            along, _ = axis_split(pose, skeleton, j, reference)
            found = columns.setdefault("level with the neighbouring joints (default)", {})
            found.setdefault(column, []).append(abs(along))
            for name, shift in rule_shifts(skeleton, pose, skeleton.joints[j]).items():
                columns.setdefault(name, {}).setdefault(column, []).append(abs(along + shift))
            own, _ = axis_split(own_pose, skeleton, j, reference)
            columns.setdefault("the estimator's own point", {}).setdefault(column, []).append(abs(own))

    for rig in ("human", "quadruped"):
        rec = simulate(SimulatorConfig(rig=rig, rate=120, noise_mm=0.5, seed=0), frames)
        skeleton = calibrate(rec.positions, rec.labels, rec.rate, joint_method="closed-form")
        estimator = calibrate(rec.positions, rec.labels, rec.rate, joint_method="closed-form",
                              hinge_placement="estimator")
        pose = solve(skeleton, rec.positions, rec.labels)
        of = dict(zip(rec.labels, rec.marker_segment, strict=True))
        seg = {s.name: of[s.markers[0]] for s in skeleton.segments}
        truth = {frozenset(pc): k for k, pc in enumerate(zip(rec.joint_parent, rec.joint_child, strict=True))}
        joints = [(j, rec.joint_centres[:, truth[frozenset((seg[x.parent], seg[x.child]))]])
                  for j, x in enumerate(skeleton.joints) if x.kind == "hinge"]
        add(f"simulated {rig} ({len(joints)} hinges)", skeleton, pose, solve(estimator, rec.positions, rec.labels),
            joints)
    if lower_body is not None:
        skeleton, estimator, body = lower_body
        pose = solve(skeleton, body.data.positions, body.data.labels)
        landmarks = body.landmarks()
        joints = [(body.joint_index(skeleton, f"{side} knee"), landmarks[f"{side} knee"]) for side in "LR"]
        if all(skeleton.joints[j].kind == "hinge" for j, _ in joints):
            add("real knees (2)", skeleton, pose, solve(estimator, body.data.positions, body.data.labels), joints)
    names = list(next(iter(columns.values())))
    print("| rule | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    for rule, values in columns.items():
        print(f"| {rule} | " + " | ".join(f"{np.mean(values[n]):.1f}" for n in names) + " |")


def cmu() -> None:
    """What the CMU files give: segments against the expert's, joints, marker fit; the segments in full."""
    print("\n## Real: CMU 41-marker set (2-4 markers per limb, several on joints)\n")
    print("| file | estimator | segments | expert segments found | joints | marker fit | calibrate s |")
    print("|---|---|---|---|---|---|---|")
    details = []
    for name in ("cmu_85_02.c3d", "cmu_85_12_breakdance.c3d"):
        if not (_common.DATA / name).is_file():
            continue
        data = read_markers(_common.DATA / name)
        for method in METHODS:
            try:
                skeleton, seconds = _common.timed(calibrate, data.positions, data.labels, data.rate,
                                                  joint_method=method)
            except Exception as exc:  # the error is the result
                print(f"| {name} | {method} | error: {exc} | | | | |")
                continue
            pose = solve(skeleton, data.positions, data.labels)
            found = [seg for seg, markers in EXPERT_CMU.items()
                     if sorted(markers) in [sorted(s.markers) for s in skeleton.segments]]
            print(f"| {name} | {method} | {len(skeleton.segments)} | {len(found)} of {len(EXPERT_CMU)} | "
                  f"{len(skeleton.joints)} | {np.nanmean(pose.residual):.1f} | {seconds:.2f} |")
            details.append(f"- {name}, {method}: " + "; ".join(" ".join(s.markers) for s in skeleton.segments)
                           + ". Joints: " + ", ".join(f"{_short(skeleton, j.parent)}-{_short(skeleton, j.child)}"
                                                      for j in skeleton.joints))
    print("\n" + "\n".join(details))


def _short(skeleton: SkeletonModel, segment: str) -> str:
    """A segment named by its first marker, readable where segment names are generic."""
    return next(s.markers[0] for s in skeleton.segments if s.name == segment)


def main() -> None:
    """Every table of the accuracy sections of docs/skeleton-generation.md."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=2000, help="simulated frames per case")
    args = parser.parse_args()
    simulated(args.frames)
    lower_body = None
    if (_common.DATA / LOWER_BODY).is_file():
        body = LowerBody(read_markers(_common.DATA / LOWER_BODY))
        skeletons, times = {}, {}
        for method in METHODS:
            skeletons[method], times[method] = _common.timed(calibrate, body.data.positions, body.data.labels,
                                                     body.data.rate, joint_method=method)
        real_lower_body(skeletons, times, body)
        estimator = calibrate(body.data.positions, body.data.labels, body.data.rate, joint_method="closed-form",
                              hinge_placement="estimator")
        lower_body = (skeletons["closed-form"], estimator, body)
    else:
        print(f"\n{_common.DATA} is absent: no real-data figures")
    hinge_rules(args.frames, lower_body)
    cmu()


if __name__ == "__main__":
    main()
