"""Simulator cost per frame (CPU time, so a busy machine does not inflate it). Run: python benchmarks/simulator.py"""

from __future__ import annotations

import time

import _common
import numpy as np

from mocapflow.io.bvh import read_bvh
from mocapflow.mocap.simulator import Simulator, SimulatorConfig

BVH = _common.DATA / "cmu_131_01.bvh"


def cost(sim: Simulator, batches: int = 10, n: int = 300) -> tuple[float, float]:
    sim.frame(0)
    times = []
    for b in range(batches):
        t = time.process_time()
        for i in range(b * n, (b + 1) * n):
            sim.frame(i)
        times.append((time.process_time() - t) / n * 1e6)
    return float(np.min(times)), float(np.median(times))


def show(label: str, sim: Simulator) -> None:
    best, median = cost(sim)
    print(f"{label:50s} best {best:5.0f} us  median {median:5.0f} us per frame")


def main() -> None:
    for rig in ("human", "rods", "quadruped"):
        show(f"{rig}: labelled, 0.5 mm noise", Simulator(SimulatorConfig(rig=rig, noise_mm=0.5)))
        hard = dict(rig=rig, unlabelled=True, ghosts=3, dropout_rate=1, long_gaps=2)
        show(f"{rig}: unlabelled, 3 ghosts, dropouts, long gaps", Simulator(SimulatorConfig(**hard)))
        show(f"{rig}: same + 5 mm skin artefact", Simulator(SimulatorConfig(**hard, skin_mm=5)))
    if BVH.is_file():
        bvh = read_bvh(BVH)
        show("human driven by cmu_131_01.bvh, unlabelled, 3 ghosts",
             Simulator(SimulatorConfig(bvh=str(BVH), unlabelled=True, ghosts=3), bvh))


if __name__ == "__main__":
    main()
