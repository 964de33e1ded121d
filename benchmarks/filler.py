"""Occlusion filler speed: offline frames per second and live per-frame cost, for 40-odd markers.

Run: python benchmarks/filler.py. Throughput is CPU time on one core (BLAS threads pinned to one), so a busy machine
does not inflate it; per-frame latencies are wall-clock times of single ``GapFiller.update`` calls (their tail grows
on a loaded machine). The first cases are the quickstart's stream (deployments/quickstart.yaml: the simulated human
at 240 Hz, unlabelled, with ghosts and gaps, labelled by the streaming labeller with the filler's predictions fed
back, as the live graph does) filled as the live filler fills it, learning its skeleton and with a calibrated one,
with and without the learnt kinematic model: their median per-frame cost is set against the live budget of 100 us.
After the table come the causal throughput for 40 markers with gaps against its target of 5,000 frames/s, and the
Kalman bank alone: its cost per frame barely grows with the number of markers because one batched predict and update
serve them all.
"""

from __future__ import annotations

import time

import _common
import numpy as np

from mocapflow.io.markers import read_markers
from mocapflow.mocap.calibration import calibrate
from mocapflow.mocap.filling import FillerConfig, GapFiller
from mocapflow.mocap.kalman import ConstantVelocityBank
from mocapflow.mocap.labelling import Labeller, LabellerConfig
from mocapflow.mocap.model import SkeletonModel
from mocapflow.mocap.rigs import make_rig
from mocapflow.mocap.simulator import SimulatorConfig, simulate, truth_skeleton

QUICKSTART = SimulatorConfig(rig="human", rate=240, noise_mm=0.5, unlabelled=True, ghosts=1, dropout_rate=0.2,
                             long_gaps=0.5, seed=3)  # deployments/quickstart.yaml's tracker
LIVE_BUDGET_US = 100  # per frame, for 52 markers with ghosts and gaps
CAUSAL_TARGET_FPS = 5000  # for 40 markers with gaps, on one core


def labelled_stream(frames: int) -> tuple[list[tuple[list[str], np.ndarray]], float]:
    """The quickstart's labelled stream, from its first confirmed marker on: per frame the labels confirmed so far
    and their positions (NaN where not seen), the filler's predictions fed back to the labeller."""
    rec = simulate(QUICKSTART, frames)
    assert rec.points is not None
    labeller = Labeller(LabellerConfig(), rec.rate)
    filler: GapFiller | None = None
    stream = []
    for f, points in enumerate(rec.points):
        predicted = None
        if filler is not None:
            predicted = np.full((len(labeller.labels), 3), np.nan)
            predicted[: len(filler.labels)] = filler.predict_next()
        positions = labeller.update(points, f / rec.rate, predicted).positions
        labels = list(labeller.labels)
        if labels:  # the filler starts with the first confirmed marker
            stream.append((labels, positions))
        if labels and filler is None:
            filler = GapFiller(labels, rec.rate, FillerConfig(kinematic_model=False))
        elif filler is not None and labels != filler.labels:
            filler.grow(labels)
        if filler is not None:
            filler.update(positions)
    return stream, rec.rate


def measure(stream: list[tuple[list[str], np.ndarray]], rate: float, config: FillerConfig,
            skeleton: SkeletonModel | None) -> tuple[float, np.ndarray, float]:
    """Frames/s (CPU time), per-frame wall times (us) and the share of samples filled, for a stream of frames each
    with its labels (which may grow, as from a labeller)."""
    filler: GapFiller | None = None
    times = np.empty(len(stream))
    filled = missing = 0
    cpu = time.process_time()
    for f, (labels, positions) in enumerate(stream):
        start = time.perf_counter_ns()
        if filler is None:
            filler = GapFiller(labels, rate, config, skeleton)
        elif labels != filler.labels:
            filler.grow(labels)
        result = filler.update(positions)
        times[f] = (time.perf_counter_ns() - start) / 1000
        filled += int((result.flags >= 2).sum())
        missing += int((~np.isfinite(positions).all(-1)).sum())
    cpu = time.process_time() - cpu
    return len(stream) / cpu, times, filled / max(missing, 1)


def show(name: str, stream: list[tuple[list[str], np.ndarray]], rate: float, config: FillerConfig,
         skeleton: SkeletonModel | None) -> tuple[float, float]:
    """Print one row; returns frames/s and the median per-frame wall time (us)."""
    fps, times, share = measure(stream, rate, config, skeleton)
    missing = 100 * np.mean([(~np.isfinite(positions).all(-1)).mean() for _, positions in stream])
    print(f"{name:<60} {len(stream[-1][0]):>7} {missing:>8.1f} {fps:>9,.0f} {np.mean(times):>8.0f} "
          f"{np.percentile(times, 50):>6.0f} {np.percentile(times, 99):>6.0f} {100 * share:>7.1f}")
    return fps, float(np.percentile(times, 50))


def frames_of(positions: np.ndarray, labels: list[str]) -> list[tuple[list[str], np.ndarray]]:
    return [(labels, x) for x in positions]


def main() -> None:
    print(f"{'case':<60} {'markers':>7} {'missing%':>8} {'frames/s':>9} {'mean us':>8} {'p50':>6} {'p99':>6} "
          f"{'filled%':>7}")
    stream, rate = labelled_stream(2400)
    labels = stream[-1][0]
    whole = np.full((len(stream), len(labels), 3), np.nan)
    for f, (seen, positions) in enumerate(stream):
        whole[f, : len(seen)] = positions
    calibrated_live = calibrate(whole[round(rate):], labels, rate, joint_method="variance")
    live = {}
    for kinematic in (False, True):
        config = FillerConfig(kinematic_model=kinematic)
        model = "kinematic model" if kinematic else "no kinematic model"
        live["learning", kinematic] = show(f"quickstart stream, learning, {model}", stream, rate, config, None)[1]
        live["calibrated", kinematic] = show(f"quickstart stream, calibrated skeleton, {model}", stream, rate,
                                             config, calibrated_live)[1]
    rec = simulate(SimulatorConfig(rig="human", rate=120, noise_mm=0.5, seed=2), 3600)
    skeleton = truth_skeleton(make_rig("human"), rec.true_positions[0])
    gappy = simulate(SimulatorConfig(rig="human", rate=120, noise_mm=0.5, seed=2, dropout_rate=0.2, long_gaps=2.0,
                                     hidden_segments=["left_forearm", "right_shank"]), 3600)
    show("simulated human, complete, skeleton", frames_of(rec.positions, rec.labels), rec.rate, FillerConfig(),
         skeleton)
    gappy_frames = frames_of(gappy.positions, gappy.labels)
    show("simulated human, dropouts + long gaps + hidden, skeleton", gappy_frames, gappy.rate, FillerConfig(),
         skeleton)
    show("simulated human, dropouts + long gaps + hidden, learning", gappy_frames, gappy.rate, FillerConfig(), None)
    show("simulated human, dropouts + long gaps + hidden, Kalman only", gappy_frames, gappy.rate,
         FillerConfig(learn=False), None)
    causal = None
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
        fps = show(f"{file}, 3 s gaps, calibrated skeleton", frames_of(x, data.labels), data.rate, FillerConfig(),
                   calibrated)[0]
        causal = (file, data.n_markers, fps) if causal is None else causal
        show(f"{file}, 3 s gaps, learning", frames_of(x, data.labels), data.rate, FillerConfig(), None)

    print(f"\nLive per-frame cost on the quickstart stream (median wall time, budget {LIVE_BUDGET_US} us):")
    for (skeleton_kind, kinematic), median in live.items():
        verdict = "within" if median <= LIVE_BUDGET_US else "over"
        print(f"  {skeleton_kind:<10} {'with' if kinematic else 'without'} kinematic model: {median:6.0f} us "
              f"({verdict} budget)")
    if causal is not None:
        file, markers, fps = causal
        verdict = "met" if fps >= CAUSAL_TARGET_FPS else "NOT met"
        print(f"Causal fill, {markers} markers with gaps ({file}, calibrated skeleton): {fps:,.0f} frames/s on one "
              f"core, target >= {CAUSAL_TARGET_FPS:,}: {verdict}")

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
