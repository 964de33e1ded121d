"""Speed of marker file input and output: real recordings and a long synthetic one, C3D and TRC, read and write.

Run as ``python benchmarks/io.py``; prints the best of several runs for each file and operation.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import _common
import numpy as np

from mocapflow.io.c3d import read_c3d, write_c3d
from mocapflow.io.markers import MarkerData
from mocapflow.io.trc import read_trc, write_trc

REAL = ["cmu_85_02.c3d", "lowerbody_clusters_knee_0401.c3d", "cmu_85_12_breakdance.c3d"]
REPEATS = 5


def best_of(operation: Callable[..., object], *args: object) -> float:
    """Shortest wall time of REPEATS calls, in seconds: the one least disturbed by other work on the machine."""
    times = []
    for _ in range(REPEATS):
        start = time.perf_counter()
        operation(*args)
        times.append(time.perf_counter() - start)
    return min(times)


def long_synthetic() -> MarkerData:
    rng = np.random.default_rng(0)
    positions = np.cumsum(rng.normal(0.0, 2.0, (20_000, 60, 3)), axis=0)
    positions[rng.random((20_000, 60)) < 0.01] = np.nan
    return MarkerData(positions, [f"M{i:02d}" for i in range(60)], 200.0, 1)


def main() -> None:
    paths = [_common.DATA / name for name in REAL]
    recordings = [(path.name, path, read_c3d(path)) for path in paths if path.is_file()]
    print(f"{'recording':34} {'frames':>7} {'markers':>7} {'read c3d':>9} {'write c3d':>9} {'write trc':>9} "
          f"{'read trc':>9}  (s, best of {REPEATS})")
    with tempfile.TemporaryDirectory() as folder:
        c3d_path, trc_path = Path(folder) / "out.c3d", Path(folder) / "out.trc"
        recordings.append(("synthetic 20000 x 60", c3d_path, long_synthetic()))
        for name, source, data in recordings:
            write_c3d_s = best_of(write_c3d, c3d_path, data)
            read_c3d_s = best_of(read_c3d, source)
            write_trc_s = best_of(write_trc, trc_path, data)
            read_trc_s = best_of(read_trc, trc_path)
            print(f"{name:34} {data.n_frames:7d} {data.n_markers:7d} {read_c3d_s:9.3f} {write_c3d_s:9.3f} "
                  f"{write_trc_s:9.3f} {read_trc_s:9.3f}")


if __name__ == "__main__":
    main()
