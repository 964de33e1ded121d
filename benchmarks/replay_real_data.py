"""Real captures through the live pipeline at their native rate: deployments/c3d-replay.yaml on each shared C3D file.

Run as ``python benchmarks/replay_real_data.py`` (about 80 s: the files are replayed in real time). For each file it
prints the frames in the file and in the recording, samples the file has but the recording lacks, the frames with
joint centres (the skeleton is learnt online: none before the joint estimator's first model), and per node the frames
in and out, the drops, the errors and the latency from the tracker's capture timestamp (p50 / p99 over the node's last
4096 frames), as the launcher's final table gives them.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _common
import numpy as np
import yaml

from mocapflow.io.markers import read_markers

FILES = ["cmu_85_02.c3d", "lowerbody_clusters_knee_0401.c3d", "cmu_85_12_breakdance.c3d"]


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"



def replay(source: Path, work: Path) -> tuple[str, float, int]:
    """Run the deployment on ``source`` with its own router and key prefix: the launcher's output, wall time, exit."""
    graph = yaml.safe_load((_common.ROOT / "deployments" / "c3d-replay.yaml").read_text())
    endpoint = free_endpoint()
    graph["name"] = f"bench{endpoint.rsplit(':', 1)[1]}"
    graph["prefix"] = f"mocapflow/{graph['name']}"
    graph["zenoh"] = {"listen": [endpoint]}
    path = work / "graph.yaml"
    path.write_text(yaml.safe_dump(graph, sort_keys=False))
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "mocapflow.cli", "run", str(path), "--set", f"tracker.path={source}",
                           "--set", f"recorder.path={work / 'out.c3d'}", "--summary", str(work / "summary.json")],
                          cwd=work, capture_output=True, text=True,
                          check=False)
    return done.stdout, time.perf_counter() - start, done.returncode


def main() -> None:
    for name in FILES:
        source = _common.DATA / name
        if not source.is_file():
            print(f"{name}: absent from {_common.DATA}, skipped")
            continue
        data = read_markers(source)
        with tempfile.TemporaryDirectory() as tmp:
            out, wall, code = replay(source, Path(tmp))
            if code != 0:
                print(f"{name}: the run failed (exit {code})\n{out}")
                continue
            live = read_markers(Path(tmp) / "out.c3d")
            nodes = json.loads((Path(tmp) / "summary.json").read_text())
        seen = np.isfinite(data.positions).all(-1)
        lost = int((seen & ~np.isfinite(live.positions).all(-1)).sum()) if live.positions.shape[:2] == seen.shape \
            else seen.sum()
        posed = int(np.isfinite(np.stack(list(live.extra.values()), axis=1)).all(-1).any(1).sum()) if live.extra else 0
        print(f"\n{name}: {data.n_frames} frames x {data.n_markers} markers at {data.rate:g} Hz "
              f"({data.n_frames / data.rate:.1f} s), run {wall:.1f} s")
        print(f"  recorded {live.n_frames} frames; samples in the file missing from the recording: {lost}; "
              f"frames with joint centres: {posed} ({len(live.extra)} joints over the run)")
        print(f"  {'node':<10} {'rate Hz':>8} {'in':>6} {'out':>6} {'drops':>6} {'errors':>6} {'p50 ms':>7} "
              f"{'p99 ms':>7}")
        for node, n in nodes.items():
            print(f"  {node:<10} {n['rate_hz']:>8.1f} {n['frames_in']:>6} {n['frames_out']:>6} {n['drops']:>6} "
                  f"{n['errors']:>6} {n['latency_p50_ms']:>7.2f} {n['latency_p99_ms']:>7.2f}")


if __name__ == "__main__":
    main()
