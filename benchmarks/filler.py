"""Occlusion filler speed: offline frames per second and live per-frame cost, for 40-odd markers.

Run: python benchmarks/filler.py. Throughput is CPU time on one core (BLAS threads pinned to one), so a busy machine
does not inflate it; per-frame latencies are wall-clock times of single ``GapFiller.update`` calls (their tail grows
on a loaded machine). The last table shows the Kalman bank alone: its cost per frame barely grows with the number of
markers because one batched predict and update serve them all.
"""

from __future__ import annotations

import time

import _common
import numpy as np

from mocapflow.io.markers import read_markers
from mocapflow.mocap.calibration import calibrate
from mocapflow.mocap.filling import FillerConfig, GapFiller
from mocapflow.mocap.kalman import ConstantVelocityBank
from mocapflow.mocap.model import SkeletonModel
from mocapflow.mocap.rigs import make_rig
from mocapflow.mocap.simulator import SimulatorConfig, simulate, truth_skeleton


def measure(positions: np.ndarray, labels: list[str], rate: float, config: FillerConfig,
            skeleton: SkeletonModel | None) -> tuple[float, np.ndarray, float]:
    """Frames/s (CPU time), per-frame wall times (us) and the share of samples filled."""
    filler = GapFiller(labels, rate, config, skeleton)
    times = np.empty(len(positions))
    filled = 0
    cpu = time.process_time()
    for f in range(len(positions)):
        start = time.perf_counter_ns()
        result = filler.update(positions[f])
        times[f] = (time.perf_counter_ns() - start) / 1000
        filled += int((result.flags >= 2).sum())
    cpu = time.process_time() - cpu
    missing = int((~np.isfinite(positions).all(-1)).sum())
    return len(positions) / cpu, times, filled / max(missing, 1)


def show(name: str, positions: np.ndarray, labels: list[str], rate: float, config: FillerConfig,
         skeleton: SkeletonModel | None) -> None:
    fps, times, share = measure(positions, labels, rate, config, skeleton)
    missing = 100 * (~np.isfinite(positions).all(-1)).mean()
    print(f"{name:<56} {len(labels):>7} {missing:>8.1f} {fps:>9,.0f} {np.mean(times):>8.0f} "
          f"{np.percentile(times, 50):>6.0f} {np.percentile(times, 99):>6.0f} {100 * share:>7.1f}")


def main() -> None:
    print(f"{'case':<56} {'markers':>7} {'missing%':>8} {'frames/s':>9} {'mean us':>8} {'p50':>6} {'p99':>6} "
          f"{'filled%':>7}")
    rec = simulate(SimulatorConfig(rig="human", rate=120, noise_mm=0.5, seed=2), 3600)
    skeleton = truth_skeleton(make_rig("human"), rec.true_positions[0])
    gappy = simulate(SimulatorConfig(rig="human", rate=120, noise_mm=0.5, seed=2, dropout_rate=0.2, long_gaps=2.0,
                                     hidden_segments=["left_forearm", "right_shank"]), 3600)
    show("simulated human, complete, skeleton", rec.positions, rec.labels, rec.rate, FillerConfig(), skeleton)
    show("simulated human, dropouts + long gaps + hidden, skeleton", gappy.positions, gappy.labels, gappy.rate,
         FillerConfig(), skeleton)
    show("simulated human, dropouts + long gaps + hidden, learning", gappy.positions, gappy.labels, gappy.rate,
         FillerConfig(), None)
    show("simulated human, dropouts + long gaps + hidden, Kalman only", gappy.positions, gappy.labels, gappy.rate,
         FillerConfig(learn=False), None)
    for file in ("lowerbody_clusters_knee_0401.c3d", "cmu_85_02.c3d"):
        path = _common.DATA / file
        if not path.is_file():
            print(f"({path} absent: skipped)")
            continue
        data = read_markers(path)
        x = data.positions.copy()
        rng = np.random.default_rng(0)
        for m in rng.choice(data.n_markers, 6, replace=False):  # six 3 s gaps on top of the real ones
            start = int(rng.integers(0, max(data.n_frames - 3 * data.rate, 1)))
            x[start:start + round(3 * data.rate), m] = np.nan
        calibrated = calibrate(data.positions, data.labels, data.rate, joint_method="variance")
        show(f"{file}, 3 s gaps, calibrated skeleton", x, data.labels, data.rate, FillerConfig(), calibrated)
        show(f"{file}, 3 s gaps, learning", x, data.labels, data.rate, FillerConfig(), None)

    print(f"\n{'Kalman bank alone: markers':<30} {'us per predict + update':>24}")
    rng = np.random.default_rng(0)
    for n in (10, 40, 160, 640):
        bank = ConstantVelocityBank(n, 1 / 120, 5e4, 1000.0)
        z = rng.normal(0, 100, (n, 3))
        variance = np.full(n, 0.25)
        bank.update(z, variance)
        start = time.process_time()
        for _ in range(2000):
            bank.predict()
            bank.update(z, variance)
        print(f"{n:<30} {(time.process_time() - start) / 2000 * 1e6:>24.1f}")


if __name__ == "__main__":
    main()
