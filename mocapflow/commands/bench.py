"""``mocapflow bench``: codec cost, and the latency each node hop adds next to bare Zenoh in the same run;
``--pipeline``: the quickstart graph at several tracker rates, frames delivered, drops and pose latency."""

from __future__ import annotations

import argparse
import gc
import json
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import orjson
import yaml
import zenoh

from mocapflow.messages import MarkerFrame, decode, encode
from mocapflow.runtime.graph import load_graph
from mocapflow.runtime.session import open_client, open_router

QUICKSTART = Path(__file__).resolve().parents[2] / "deployments" / "quickstart.yaml"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="print codec cost per frame and per-hop latency next to bare Zenoh")
    p.add_argument("--markers", type=int, default=60, help="markers per frame (default 60)")
    p.add_argument("--rate", type=float, default=240.0, help="frame rate of the latency runs (default 240)")
    p.add_argument("--seconds", type=float, default=None,
                   help="length of each latency run (default 5; --pipeline: 20)")
    p.add_argument("--hops", type=int, default=3, help="relay nodes in the chain (default 3)")
    p.add_argument("--pipeline", action="store_true",
                   help="run a whole graph (--graph) at each of --rates instead of the relay chain")
    p.add_argument("--graph", default=str(QUICKSTART), help="graph of --pipeline (default the quickstart)")
    p.add_argument("--rates", default="240,500,1000", help="tracker rates of --pipeline, Hz (default 240,500,1000)")
    p.add_argument("--layouts", default="grouped,separate",
                   help="--pipeline: the graph as written (grouped) and/or every node in its own process (separate)")
    p.set_defaults(func=run)


def _frame(markers: int, index: int = 0) -> MarkerFrame:
    rng = np.random.default_rng(index)
    positions = (rng.normal(size=(markers, 3)) * 500).astype(np.float32)
    positions[::17] = np.nan
    return MarkerFrame(frame=index, capture_ns=time.time_ns(), rate=240.0, positions=positions,
                       labels=[f"M{i:03d}" for i in range(markers)])


def _codec(markers: int, n: int = 20_000) -> tuple[float, float, int]:
    msg = _frame(markers)
    payload = encode(msg)
    t0 = time.perf_counter()
    for _ in range(n):
        encode(msg)
    t1 = time.perf_counter()
    for _ in range(n):
        decode(payload, MarkerFrame)
    t2 = time.perf_counter()
    return (t1 - t0) / n * 1e6, (t2 - t1) / n * 1e6, len(payload)


def _free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def _percentiles(values: list[float]) -> str:
    if not values:
        return "no samples"
    p50, p99 = np.percentile(values, [50, 99])
    return f"p50 {p50:7.3f} ms   p99 {p99:7.3f} ms   (n={len(values)})"


def _bare_zenoh(markers: int, rate: float, seconds: float) -> list[float]:
    """Publisher and subscriber in two client sessions through one router: the floor any node hop builds on."""
    endpoint = _free_endpoint()
    latencies: list[float] = []
    with open_router([endpoint]), open_client([endpoint]) as pub_s, open_client([endpoint]) as sub_s:
        def on_sample(sample: zenoh.Sample) -> None:
            if sample.attachment is None:
                return
            sent = int.from_bytes(sample.attachment.to_bytes(), "little")
            latencies.append((time.time_ns() - sent) / 1e6)

        sub = sub_s.declare_subscriber("bench/bare", on_sample)
        pub = pub_s.declare_publisher("bench/bare")
        time.sleep(0.5)
        payload = encode(_frame(markers))
        period = 1.0 / rate
        t0 = time.monotonic()
        for i in range(int(seconds * rate)):
            delay = t0 + i * period - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            pub.put(payload, attachment=time.time_ns().to_bytes(8, "little"))
        time.sleep(0.3)
        sub.undeclare()
    return latencies


def _node_chain(hops: int, rate: float, seconds: float) -> dict[str, list[float]]:
    """simulator -> relay x hops, each node its own process; latency of each key from the tracker's timestamp."""
    endpoint = _free_endpoint()
    frames = int(seconds * rate)
    lines = [f"name: bench\nzenoh: {{listen: ['{endpoint}']}}\nnodes:",
             f"  tracker: {{plugin: simulator, config: {{rig: human, rate: {rate}, frames: {frames}}}}}"]
    previous = "tracker"
    for h in range(1, hops + 1):
        lines.append(f"  hop{h}: {{plugin: relay, inputs: {{markers: {previous}/markers}}}}")
        previous = f"hop{h}"
    keys = ["tracker", *[f"hop{h}" for h in range(1, hops + 1)]]
    latencies: dict[str, list[float]] = {k: [] for k in keys}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.yaml"
        path.write_text("\n".join(lines) + "\n")
        run = subprocess.Popen([sys.executable, "-m", "mocapflow.cli", "run", str(path)], stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
        try:
            time.sleep(1.0)
            with open_client([endpoint]) as session:
                def listener(key: str) -> Callable[[zenoh.Sample], None]:
                    def on_sample(sample: zenoh.Sample) -> None:
                        if sample.kind == zenoh.SampleKind.PUT:
                            msg = decode(sample.payload.to_bytes(), MarkerFrame)
                            latencies[key].append((time.time_ns() - msg.capture_ns) / 1e6)
                    return on_sample

                subs = [session.declare_subscriber(f"mocapflow/bench/{k}/markers", listener(k)) for k in keys]
                out, _ = run.communicate(timeout=seconds + 60)
                for s in subs:
                    s.undeclare()
        finally:
            if run.poll() is None:
                run.terminate()
                run.wait()
    if run.returncode != 0:
        raise RuntimeError(f"benchmark graph failed:\n{out}")
    return latencies


def _pipeline(graph: str, rate: float, seconds: float, separate: bool) -> dict[str, Any]:
    """Run ``graph`` with its tracker at ``rate`` for ``seconds`` of frames, through a router of its own, and watch
    from outside its filled markers (every frame should arrive, in order) and its poses (latency from capture; they
    start once the skeleton is learnt), with every node's drops and backlog from ``--summary``. ``separate``: every
    node in its own process (the graph's groups removed)."""
    endpoint = _free_endpoint()
    prefix = load_graph(graph).key_prefix
    frames = int(seconds * rate)
    seen: dict[str, list[tuple[int, float]]] = {"filler/markers": [], "skeleton/pose": []}

    def listener(key: str) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.PUT:
                now = time.time_ns()
                head = orjson.loads(sample.payload.to_bytes())
                seen[key].append((head["frame"], (now - head["capture_ns"]) / 1e6))
        return on_sample

    with tempfile.TemporaryDirectory() as tmp, open_router([endpoint]) as router:
        subs = [router.declare_subscriber(f"{prefix}/{key}", listener(key)) for key in seen]
        if separate:
            raw = yaml.safe_load(Path(graph).read_text())
            for node in raw["nodes"].values():
                node.pop("group", None)
            graph = str(Path(tmp) / Path(graph).name)
            Path(graph).write_text(yaml.safe_dump(raw))
        summary = Path(tmp) / "summary.json"
        cmd = [sys.executable, "-m", "mocapflow.cli", "run", graph, "--connect", endpoint, "--summary", str(summary),
               "--set", f"tracker.rate={rate}", "--set", f"tracker.frames={frames}",
               "--set", f"recorder.path={Path(tmp) / 'out.c3d'}"]
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=seconds * 10 + 120, check=False)
        time.sleep(0.5)
        for sub in subs:
            sub.undeclare()
        nodes = json.loads(summary.read_text()) if summary.exists() else {}
    if run.returncode != 0:
        print(f"  the graph exited {run.returncode}: " + " | ".join(run.stdout.strip().splitlines()[-3:]))
    markers = [f for f, _ in seen["filler/markers"]]
    poses = [f for f, _ in seen["skeleton/pose"]]
    return {
        "frames": frames, "delivered": len(set(markers)), "in_order": markers == sorted(markers),
        "poses": len(poses), "pose_frames": poses[-1] - poses[0] + 1 if poses else 0,
        "drops": sum(int(n.get("drops", 0)) for n in nodes.values()),
        "skipped": sum(int(n.get("skipped", 0)) for n in nodes.values()),
        "latency": [lat for _, lat in seen["skeleton/pose"]],
        "filled": [lat for _, lat in seen["filler/markers"]],
        "seconds": _by_second(seen["filler/markers"], rate, poses[0] if poses else None),
        "filler": tuple(nodes.get("filler", {}).get(f"latency_{p}_ms") for p in ("p50", "p99")),
        "backlog_max_ms": {n: v["backlog_max_ms"] for n, v in nodes.items() if v.get("backlog_max_ms")},
    }


def _by_second(latencies: list[tuple[int, float]], rate: float, first_pose: int | None) -> str:
    """The p99 latency of each second of capture (by frame number), '|' before the second of the first pose: where
    in a run the tail lies, before the skeleton model and with it."""
    per: dict[int, list[float]] = {}
    for frame, latency in latencies:
        per.setdefault(int(frame // rate), []).append(latency)
    marks = {int(first_pose // rate)} if first_pose is not None else set()
    return " ".join(("| " if s in marks else "") + f"{np.percentile(v, 99):.1f}" for s, v in sorted(per.items()))


def run_pipeline(args: argparse.Namespace) -> int:
    rates = [float(r) for r in args.rates.split(",") if r.strip()]
    print(f"{Path(args.graph).name}, {args.seconds:g} s of frames at each rate; latency from capture, all processes on"
          " this machine")
    layouts = [x.strip() for x in args.layouts.split(",") if x.strip()]
    for rate in rates:
        bare = _bare_zenoh(args.markers, rate, min(args.seconds, 5.0))
        bare_p99 = float(np.percentile(bare, 99)) if bare else float("nan")
        # the live-speed targets: at 240 Hz a pose within 5 ms; at 1000 Hz within 3 x (4 hops of bare Zenoh) + 1 ms
        target = 5.0 if rate == 240 else 3 * 4 * bare_p99 + 1 if rate == 1000 else None
        print(f"{rate:6g} Hz  bare Zenoh   {_percentiles(bare)}" +
              ("" if target is None else f"   target: pose p99 <= {target:.2f} ms"))
        for layout in layouts:
            result = _pipeline(args.graph, rate, args.seconds, separate=layout == "separate")
            print(f"  {layout:<9} pose         {_percentiles(result['latency'])}   poses {result['poses']} of frames "
                  f"{result['pose_frames']} since the first")
            print(f"{'':12}filled       {_percentiles(result['filled'])}" + (
                "" if None in result["filler"] else  # the rest is the way out: Zenoh's threads and the router
                f"   as the filler put them: p50 {result['filler'][0]:.3f} ms, p99 {result['filler'][1]:.3f} ms"))
            print(f"{'':12}filled p99 by second of capture, ms ('|': the first pose): {result['seconds']}")
            print(f"{'':12}filled markers: frames {result['delivered']}/{result['frames']}"
                  f"{'' if result['in_order'] else ' (OUT OF ORDER)'}, drops {result['drops']}, skipped "
                  f"{result['skipped']}; longest wait in an inbox: " +
                  (", ".join(f"{n} {v:.1f} ms" for n, v in result["backlog_max_ms"].items()) or "none"))
    return 0


def run(args: argparse.Namespace) -> int:
    gc.freeze()  # as the nodes do (runtime.worker): no full pass of the collector delays the timing callbacks
    if args.pipeline:
        args.seconds = args.seconds or 20.0
        return run_pipeline(args)
    args.seconds = args.seconds or 5.0
    enc, dec, size = _codec(args.markers)
    print(f"codec, {args.markers}-marker frame ({size} bytes JSON): encode {enc:.1f} us, decode {dec:.1f} us,"
          f" round trip {enc + dec:.1f} us")
    print(f"latency at {args.rate:g} Hz over {args.seconds:g} s, all processes on this machine:")
    bare = _bare_zenoh(args.markers, args.rate, args.seconds)
    print(f"  bare Zenoh put -> subscribe (via router)  {_percentiles(bare)}")
    chain = _node_chain(args.hops, args.rate, args.seconds)
    previous = None
    for key, values in chain.items():
        print(f"  {key + '/markers':<40} {_percentiles(values)}")
        if previous is not None and values and chain[previous]:
            hop = np.percentile(values, 50) - np.percentile(chain[previous], 50)
            print(f"    added by {key} (receive, decode, process, encode, publish): p50 {hop:.3f} ms")
        previous = key
    return 0
