"""What the Rerun viewer sink costs the pipeline: pose latency with and without it, on the same graph at 1000 Hz.

Run as ``python benchmarks/viewer_cost.py [--seconds S] [--rounds N] [--speed X]`` (about 4 x N x (S + 10) s). The
real lower-body capture (100 Hz) is replayed ten times as fast, looping, through deployments/c3d-replay.yaml with a
calibrated skeleton and without the online clusterer and the recorder (whose bursts would swamp what is measured), so
a pose is solved for each of the 1000 frames a second (``--speed``: a machine that cannot keep up with 1000 Hz is
measured at a rate it sustains). Each round runs the graph four times, in turn: without a viewer; with the ``rerun``
sink on the filled markers, the pose and the skeleton, drawing at its default 60 Hz into an .rrd file; the same with
the sink's process on CPU time the pipeline leaves (``cpu: idle``); and, the worst case, with the sink on the whole
streams instead of their previews (``queue: latest``) drawing every frame it receives (``rate: null``). Per run it
prints the skeleton node's pose latency from the tracker's capture timestamp (p50 / p99 over its last 4096
frames, as the launcher's summary gives them), its poses, drops and rate, and the frames the sink received.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT.parent / "shared" / "data" / "lowerbody_clusters_knee_0401.c3d"
CLI = [sys.executable, "-m", "mocapflow.cli"]
VARIANTS: dict[str, dict[str, Any] | None] = {  # the sink's node settings (its config under "config")
    "no viewer": None, "rerun 60 Hz": {}, "rerun 60 Hz, cpu idle": {"cpu": "idle"},
    "rerun every frame": {"config": {"rate": None}, "queue": {"markers": "latest", "pose": "latest"}}}


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def run(work: Path, skeleton: Path, viewer: dict[str, Any] | None, seconds: float, speed: float) -> dict[str, Any]:
    graph = yaml.safe_load((ROOT / "deployments" / "c3d-replay.yaml").read_text())
    endpoint = free_endpoint()
    graph["name"] = f"viewercost{endpoint.rsplit(':', 1)[1]}"
    graph["prefix"] = f"mocapflow/{graph['name']}"
    graph["zenoh"] = {"listen": [endpoint]}
    for node in ("clusterer", "recorder"):
        del graph["nodes"][node]
    del graph["nodes"]["joints"]["inputs"]["segments"]
    if viewer is not None:
        graph["nodes"]["viewer"] = {
            **viewer, "plugin": "rerun", "config": {"save": str(work / "scene.rrd"), **viewer.get("config", {})},
            "inputs": {"markers": "filler/markers", "pose": "skeleton/pose", "skeleton": "joints/skeleton"}}
    path = work / "graph.yaml"
    path.write_text(yaml.safe_dump(graph, sort_keys=False))
    summary = work / "summary.json"
    subprocess.run([*CLI, "run", str(path), "--duration", str(seconds), "--summary", str(summary),
                    "--set", f"tracker.path={SOURCE}", "--set", f"tracker.speed={speed}", "--set", "tracker.loop=true",
                    "--set", f"skeleton.skeleton={skeleton}", "--set", "joints.refine=false"],
                   cwd=work, capture_output=True, text=True, check=False, env={**os.environ, "RERUN_ANALYTICS": "0"})
    return json.loads(summary.read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="length of each run")
    parser.add_argument("--rounds", type=int, default=2, help="runs of each variant, interleaved")
    parser.add_argument("--speed", type=float, default=10.0, help="replay speed; 10 is 1000 Hz")
    args = parser.parse_args()
    if not SOURCE.is_file():
        sys.exit(f"{SOURCE}: absent; this benchmark needs the shared data folder")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        skeleton = work / "skeleton.json"
        subprocess.run([*CLI, "calibrate", str(SOURCE), "-o", str(skeleton)], check=True, capture_output=True)
        print(f"{SOURCE.name} at {100 * args.speed:.0f} Hz, {args.seconds:.0f} s per run")
        print(f"{'run':<22}{'pose p50 ms':>12}{'pose p99 ms':>12}{'poses':>8}{'drops':>7}{'pose Hz':>9}"
              f"{'viewer in':>10}")
        for round_ in range(args.rounds):
            for name, viewer in VARIANTS.items():
                nodes = run(work, skeleton, viewer, args.seconds, args.speed)
                pose = nodes["skeleton"]
                p50, p99 = ("-" if v is None else f"{v:.2f}" for v in (pose["latency_p50_ms"], pose["latency_p99_ms"]))
                print(f"{name + f' #{round_ + 1}':<22}{p50:>12}{p99:>12}"
                      f"{pose['frames_out']:>8}{pose['drops']:>7}{pose['rate_hz']:>9.0f}"
                      f"{nodes.get('viewer', {}).get('frames_in', '-'):>10}", flush=True)


if __name__ == "__main__":
    main()
