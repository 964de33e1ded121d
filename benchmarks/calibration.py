"""Skeleton generation: time and accuracy against the simulator's truth, and what the real files give.

Run: python benchmarks/calibration.py [--quick]. Times are CPU seconds on one core (BLAS threads pinned to one), so
a busy machine does not inflate them.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from mocapflow.mocap.calibration import calibrate  # noqa: E402
from mocapflow.mocap.clustering import SegmentTracker  # noqa: E402
from mocapflow.mocap.model import SkeletonModel  # noqa: E402
from mocapflow.mocap.rigid import bone_lengths  # noqa: E402
from mocapflow.mocap.simulator import SimRecording, SimulatorConfig, simulate  # noqa: E402
from mocapflow.mocap.solve import solve  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def timed(fn, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN201
    start = time.process_time()
    out = fn(*args, **kwargs)
    return out, time.process_time() - start


def score(rec: SimRecording, skeleton: SkeletonModel, labels: list[str]) -> dict:
    """Partition and tree against the truth, and mean solved-joint error per joint kind (mm)."""
    of = dict(zip(rec.labels, rec.marker_segment, strict=True))
    truth_groups = sorted(sorted(m for m in labels if of[m] == s) for s in {of[m] for m in labels})
    groups_ok = sorted(sorted(s.markers) for s in skeleton.segments) == truth_groups
    seg = {s.name: of[s.markers[0]] for s in skeleton.segments}
    true_edges = {frozenset(pc): k for k, pc in enumerate(zip(rec.joint_parent, rec.joint_child, strict=True))}
    edges = [frozenset((seg[j.parent], seg[j.child])) for j in skeleton.joints]
    present = {s for s in of.values() if any(of[m] == s for m in labels)}
    tree_ok = set(edges) == {e for e in true_edges if e <= present}
    index = [rec.labels.index(m) for m in labels]
    pose, solve_s = timed(solve, skeleton, rec.positions[:, index], labels)
    errors: dict[str, list[float]] = {"ball": [], "hinge": []}
    for j, (joint, edge) in enumerate(zip(skeleton.joints, edges, strict=True)):
        if edge in true_edges:
            e = np.linalg.norm(pose.joint_centres[:, j] - rec.joint_centres[:, true_edges[edge]], axis=1)
            errors[joint.kind].append(float(np.nanmean(e)))
    return dict(groups=groups_ok, tree=tree_ok, solve=solve_s, errors=errors)


def simulated(frames: int, quick: bool) -> None:
    print(f"simulated rigs, 120 Hz, {frames} frames, 0.5 mm noise (seed 0); errors are mean distances between solved "
          "and true joint centres over all frames, mm")
    print(f"{'case':<42} {'markers':>7} {'calib s':>8} {'solve s':>8} {'groups':>6} {'tree':>5} "
          f"{'ball mean':>9} {'ball max':>8} {'hinge mean':>10} {'hinge max':>9}")
    cases = [("human", {}), ("rods", {}), ("quadruped", {}), ("quadruped, first 28 markers", {}),
             ("human, 5 mm soft-tissue artefact", {"skin_mm": 5.0}),
             ("human, dropouts and long gaps", {"dropout_rate": 0.5, "long_gaps": 4.0})]
    methods = [("variance", "spectral", "neighbours"), ("closed-form", "spectral", "neighbours"),
               ("variance", "distance-threshold", "neighbours"), ("variance", "spectral", "estimator"),
               ("closed-form", "spectral", "estimator")]
    if quick:
        cases, methods = cases[:4], methods[:2]
    for name, options in cases:
        rig = name.split(",")[0]
        rec = simulate(SimulatorConfig(rig=rig, rate=120, noise_mm=0.5, seed=0, **options), frames)
        labels = rec.labels[:28] if "28" in name else rec.labels
        positions = rec.positions[:, : len(labels)]
        for joint_method, method, placement in methods:
            if ("artefact" in name or "gaps" in name) and (method, placement) != ("spectral", "neighbours"):
                continue
            skeleton, calib_s = timed(calibrate, positions, labels, rec.rate, method=method,
                                      joint_method=joint_method, hinge_placement=placement, show_progress=False)
            s = score(rec, skeleton, labels)
            ball, hinge = s["errors"]["ball"], s["errors"]["hinge"]
            label = f"{name}: {joint_method}, {method}" + (", hinge by estimator" if placement == "estimator" else "")
            print(f"{label:<42.42} {len(labels):>7} {calib_s:>8.2f} {s['solve']:>8.2f} {s['groups']!s:>6} "
                  f"{s['tree']!s:>5} {_stat(ball, np.mean):>9} {_stat(ball, np.max):>8} {_stat(hinge, np.mean):>10} "
                  f"{_stat(hinge, np.max):>9}")
            if rig == "rods" and placement == "neighbours":
                length = next(iter(bone_lengths(skeleton).values()))
                print(f"{'':<42} middle rod length {length:.2f} mm (true 359, {100 * (length / 359 - 1):+.3f} %)")


def _stat(values: list[float], fn) -> str:  # noqa: ANN001
    return f"{fn(values):.2f}" if values else "-"


def tracker(frames: int) -> None:
    rec = simulate(SimulatorConfig(rig="human", rate=120, noise_mm=0.5, seed=1), frames)
    track = SegmentTracker(rec.labels, window=600, every=10 ** 9)
    _, seconds = timed(lambda: [track.update(f) for f in rec.positions])
    print(f"\nSegmentTracker, {len(rec.labels)} markers: {1e6 * seconds / frames:.0f} us per frame (statistics only); "
          "one spectral re-clustering:", end=" ")
    from mocapflow.mocap.clustering import partition_spectral

    _, once = timed(partition_spectral, track.stats.spread())
    print(f"{1e3 * once:.1f} ms")


def real(quick: bool) -> None:
    from mocapflow.io.markers import read_markers

    path = DATA / "lowerbody_clusters_knee_0401.c3d"
    if not path.is_file():
        print(f"\n{DATA} is absent: no real-data figures")
        return
    data = read_markers(path)
    print(f"\nreal: {path.name}, {data.n_frames} frames, {data.n_markers} markers; joint centres compared with the "
          "midpoints of the medial and lateral knee and ankle markers (the usual clinical definitions), mm")

    def mid(a: str, b: str) -> np.ndarray:
        return 0.5 * (data.positions[:, data.labels.index(a)] + data.positions[:, data.labels.index(b)])

    anatomy = {"left knee": mid("LMKN", "LLKN"), "right knee": mid("RMKN", "RLKN"), "left ankle": mid("LLAK", "LMAK"),
               "right ankle": mid("RLAK", "RMAK")}
    for joint_method in ("variance", "closed-form"):
        skeleton, seconds = timed(calibrate, data.positions, data.labels, data.rate, joint_method=joint_method,
                                  show_progress=False)
        pose = solve(skeleton, data.positions, data.labels)
        part = {m: s.name for s in skeleton.segments for m in s.markers}
        found = []
        for name, point in anatomy.items():
            side, kind = name.split()
            child = part[f"{side[0].upper()}{'SH1' if kind == 'knee' else 'TOE'}"]
            j = [x.child for x in skeleton.joints].index(child)
            found.append(f"{name} {np.nanmean(np.linalg.norm(pose.joint_centres[:, j] - point, axis=1)):.1f}")
        print(f"  {joint_method:<12} {seconds:5.2f} s, {len(skeleton.segments)} segments, root {skeleton.root}, "
              f"marker fit {np.nanmean(pose.residual):.2f} mm; " + ", ".join(found))
    cmu = ["cmu_85_02.c3d"] if quick else ["cmu_85_02.c3d", "cmu_85_12_breakdance.c3d"]
    for name in cmu:
        if not (DATA / name).is_file():
            continue
        data = read_markers(DATA / name)
        skeleton, seconds = timed(calibrate, data.positions, data.labels, data.rate, show_progress=False)
        pose = solve(skeleton, data.positions, data.labels)
        print(f"\nreal: {name}, {data.n_frames} frames, {data.n_markers} markers (2-4 per limb, some on joints): "
              f"{seconds:.2f} s, {len(skeleton.segments)} segments, root {skeleton.root}, marker fit "
              f"{np.nanmean(pose.residual):.2f} mm")
        for s in skeleton.segments:
            print(f"  {s.name:<10} {' '.join(s.markers)}")
        print("  joints: " + ", ".join(f"{j.parent}-{j.child}" for j in skeleton.joints))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer cases")
    parser.add_argument("--frames", type=int, default=2000)
    args = parser.parse_args()
    simulated(args.frames, args.quick)
    tracker(args.frames)
    real(args.quick)


if __name__ == "__main__":
    main()
