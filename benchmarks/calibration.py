"""Skeleton generation speed: calibration and solving on simulated rigs, the streaming clusterer, and the real files.

Run: python benchmarks/calibration.py [--frames 2000]. Times are CPU seconds on one core (BLAS threads pinned to
one), so a busy machine does not inflate them. The thesis (Schoenauer 2007) needed 90 s for 28 markers x 2000 frames
on 4 cores; the target is under 3 s on one core. Accuracy is in benchmarks/skeleton_accuracy.py.
"""

from __future__ import annotations

import argparse

import _common

from mocapflow.io.markers import read_markers
from mocapflow.mocap.calibration import calibrate
from mocapflow.mocap.clustering import SegmentTracker, partition_spectral
from mocapflow.mocap.simulator import SimulatorConfig, simulate
from mocapflow.mocap.solve import solve

METHODS = ("auto", "closed-form", "variance")




def row(name: str, positions: object, labels: list[str], rate: float) -> None:
    frames, markers = positions.shape[:2]
    cells = []
    for method in METHODS:
        try:
            skeleton, seconds = _common.timed(calibrate, positions, labels, rate, joint_method=method)
        except Exception as exc:  # a method that does not apply is a result
            cells.append(f"- ({type(exc).__name__})")
            continue
        _, solve_s = _common.timed(solve, skeleton, positions, labels)
        cells.append(f"{seconds:.2f} / {solve_s:.2f}")
    print(f"| {name} | {markers} | {frames} | " + " | ".join(cells) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=2000)
    args = parser.parse_args()
    print("| case | markers | frames | " + " | ".join(f"{m}: calibrate / solve s" for m in METHODS) + " |")
    print("|---|---|---|" + "---|" * len(METHODS))
    for name, rig, count in (("quadruped, first 28 markers (the thesis's size)", "quadruped", 28),
                             ("rods", "rods", None), ("quadruped", "quadruped", None), ("human", "human", None)):
        rec = simulate(SimulatorConfig(rig=rig, rate=120, noise_mm=0.5, seed=0), args.frames)
        labels = rec.labels[:count] if count else rec.labels
        row(name, rec.positions[:, : len(labels)], labels, rec.rate)
    for file in ("lowerbody_clusters_knee_0401.c3d", "cmu_85_02.c3d", "cmu_85_12_breakdance.c3d", "hamner_run200.trc",
                 "sprinter_JA1Gait35.c3d"):
        if (_common.DATA / file).is_file():
            data = read_markers(_common.DATA / file)
            row(file, data.positions, data.labels, data.rate)

    rec = simulate(SimulatorConfig(rig="human", rate=120, noise_mm=0.5, seed=1), args.frames)
    tracker = SegmentTracker(rec.labels, window=600, every=10 ** 9)
    _, seconds = _common.timed(lambda: [tracker.update(f) for f in rec.positions])
    _, once = _common.timed(partition_spectral, tracker.stats.spread())
    print(f"\nSegmentTracker, {len(rec.labels)} markers: {1e6 * seconds / args.frames:.0f} us per frame (statistics), "
          f"{1e3 * once:.1f} ms per spectral re-clustering")


if __name__ == "__main__":
    main()
