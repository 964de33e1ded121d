"""Labelling benchmark: per-frame cost of the streaming labeller and accuracy against truth.

Runs the simulator's human rig and the real captures of the shared data folder (identities stripped, occlusions and
ghosts added by ``unlabel``), at a moderate and a heavy level of damage, and the human rig seen through the
simulator's camera model (4 and 8 cameras, whose body occlusions hide markers often and several at once) at the
moderate level. For each it prints the cost of ``Labeller.update`` per frame (mean, median, 99th percentile, in
microseconds of wall time), then the accuracy of the streaming labels (which leave a new track's first
``confirm_frames`` frames unlabelled) and of the offline ``label_sequence`` (those frames filled in, fragments
merged, short tracks dropped).

    python benchmarks/labelling.py [--frames N] [--data DIR]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import _common
import numpy as np

from mocapflow.mocap.evaluation import score_labelling, unlabel
from mocapflow.mocap.labelling import (
    Labeller,
    LabellerConfig,
    label_sequence,
)
from mocapflow.mocap.simulator import SimulatorConfig, simulate

# damage levels: simulator settings, and unlabel() settings (occlusions per marker per second, ghosts per frame)
LEVELS = {
    "moderate": ({"dropout_rate": 0.2, "long_gaps": 2.0, "ghosts": 2.0}, (0.05, 1.0)),
    "heavy": ({"dropout_rate": 0.5, "long_gaps": 4.0, "ghosts": 5.0}, (0.2, 3.0)),
}
CAMERAS = (4, 8)  # camera counts of the camera-model cases


def _scenarios(frames: int, data: Path) -> list[tuple[str, list[np.ndarray], list[np.ndarray], float, int]]:
    """(name, points per frame, identity per frame, rate, true marker count) for every case."""
    cases = []
    simulated = [(level, damage, 0) for level, (damage, _) in LEVELS.items()]
    simulated += [("moderate", LEVELS["moderate"][0], cameras) for cameras in CAMERAS]
    for level, damage, cameras in simulated:
        rec = simulate(SimulatorConfig(rig="human", rate=240, noise_mm=0.5, unlabelled=True, seed=7, cameras=cameras,
                                       **damage), frames)
        assert rec.points is not None and rec.identity is not None
        seen_by = f"{cameras} cameras, " if cameras else ""
        cases.append((f"simulated human 240 Hz, {seen_by}{level}", rec.points, rec.identity, rec.rate,
                      len(rec.labels)))
    if not data.is_dir():
        print(f"(real captures skipped: {data} is absent)")
        return cases
    from mocapflow.io.markers import read_markers

    for name in ("lowerbody_clusters_knee_0401.c3d", "cmu_85_02.c3d", "cmu_85_12_breakdance.c3d"):
        marker_data = read_markers(data / name)
        for level, (_, (dropouts, ghosts)) in LEVELS.items():
            points, identity = unlabel(marker_data.positions, marker_data.rate, seed=1, gaps_per_s=dropouts,
                                       ghosts=ghosts)
            cases.append((f"{name} {marker_data.rate:g} Hz, {level}", list(points), list(identity),
                          marker_data.rate, marker_data.n_markers))
    return cases


def _stream(points: list[np.ndarray], rate: float) -> tuple[np.ndarray, np.ndarray]:
    """Streaming labels (F, T, 3) and the wall time of each ``update`` call (s)."""
    labeller = Labeller(LabellerConfig(), rate)
    rows, cost = [], np.empty(len(points))
    for i, frame in enumerate(points):
        start = time.perf_counter()
        result = labeller.update(frame, i / rate)
        cost[i] = time.perf_counter() - start
        rows.append(result.positions)
    tracks = np.full((len(rows), len(labeller.labels), 3), np.nan)
    for i, row in enumerate(rows):
        tracks[i, : len(row)] = row
    return tracks, cost


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=4800, help="simulated frames per case (default 4800)")
    parser.add_argument("--data", type=Path, default=_common.DATA, help="folder of the real captures")
    args = parser.parse_args()
    for name, points, identity, rate, markers in _scenarios(args.frames, args.data):
        seen = np.mean([np.isfinite(np.asarray(p)).all(axis=1).sum() for p in points])
        tracks, cost = _stream(points, rate)
        start = time.perf_counter()
        offline, _ = label_sequence(points, rate)
        offline_s = time.perf_counter() - start
        us = cost * 1e6
        print(f"\n{name}: {len(points)} frames, {markers} markers, {seen:.1f} points per frame")
        print(f"  update cost: mean {us.mean():.0f} us, median {np.median(us):.0f} us, "
              f"p99 {np.percentile(us, 99):.0f} us; offline label_sequence {offline_s / len(points) * 1e6:.0f} us "
              "per frame")
        print(f"  streaming: {score_labelling(tracks, points, identity, markers).summary()}")
        print(f"  offline:   {score_labelling(offline, points, identity, markers).summary()}")


if __name__ == "__main__":
    main()
