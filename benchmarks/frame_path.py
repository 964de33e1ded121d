"""One frame's path through the grouped quickstart at 1000 Hz, step by step: where its latency goes.

Run as ``python benchmarks/frame_path.py [--rate HZ] [--seconds S] [--paced]`` (about 3 x S s of CPU on a quiet
machine). The nodes of deployments/quickstart.yaml are built from that file (the tracker at ``--rate``) and driven
in the order the runtime drives them: the ``frame`` group (the tracker among them) hands each frame from node to
node as Python objects, each frame followed by all it causes (the filler's prediction back to the labeller), and a
frame that leaves the group's process is encoded there and decoded in the other; the clusterer and the joint
estimator run in processes of their own and read the filled markers' sampled copy (``queue: sampled``), so only its
frames are encoded for them and decoded there; their costs are shown apart (they do not hold the frame back; their
models reach the group as they would live). Frames are produced as fast as they are handled, so each step's time is
its cost alone, with no wait in a queue; with ``--paced``, each when it is due, as a tracker gives them, the process
sleeping in between as the group's does live: what that sleep alone costs the work that follows it. Zenoh's own
transport is what ``mocapflow bench`` measures next to it. Printed: per step, the wall-clock time per call (p50 /
p99 over the frames after the skeleton model arrived) and per frame (all its calls' time, spread over the frames),
then the sum of the p50s along the frame's path and the group's whole work per frame: a process that cannot do that
work within one frame period falls behind. Last, that work by node and by second of capture, before the skeleton
model arrives and after: where in a capture the group comes near its frame period.
"""

from __future__ import annotations

import argparse
import gc
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import _common  # noqa: F401  (BLAS pinned to one thread, before numpy loads)
import numpy as np
import yaml

from mocapflow.messages import MarkerFrame, decode, encode
from mocapflow.runtime.plugins import load
from mocapflow.runtime.sampling import in_copy

QUICKSTART = _common.ROOT / "deployments" / "quickstart.yaml"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rate", type=float, default=1000.0, help="tracker rate (default 1000 Hz)")
    parser.add_argument("--seconds", type=float, default=14.0,
                        help="frames of capture to run (default 14 s: the skeleton model comes after 5 s)")
    parser.add_argument("--paced", action="store_true",
                        help="hand each frame over when it is due, as a tracker does, sleeping in between (default: "
                             "each as soon as the one before is handled)")
    args = parser.parse_args()
    graph = yaml.safe_load(QUICKSTART.read_text())["nodes"]
    graph["tracker"]["config"]["rate"] = args.rate
    sent: list[tuple[str, str, Any]] = []
    links: dict[tuple[str, str], list[tuple[str, str]]] = defaultdict(list)  # (node, output) -> inputs

    def build(name: str, publish: Any) -> Any:
        spec = graph[name]
        cls = load(spec["plugin"])
        node = cls(cls.Config.model_validate(spec.get("config", {})), publish, name)
        node.linked = frozenset(spec.get("inputs", {}))  # as the runtime tells it
        node.audience = lambda port: bool(links.get((name, port)))  # with no one watching
        return node

    with tempfile.TemporaryDirectory() as tmp:
        graph["recorder"]["config"]["path"] = str(Path(tmp) / "out.c3d")
        nodes = {name: build(name, lambda port, msg, name=name: sent.append((name, port, msg))) for name in graph}
        for name, spec in graph.items():
            for port, link in spec.get("inputs", {}).items():
                src, _, out = link.partition("/")
                links[(src, out)].append((name, port))
        group = {name for name, spec in graph.items() if spec.get("group") == "frame"}
        costs: dict[str, list[float]] = defaultdict(list)
        skeleton_at: int | None = None
        frames = int(args.seconds * args.rate)
        work: dict[str, np.ndarray] = defaultdict(lambda: np.zeros(frames))  # per group node: its time per frame
        given: dict[str, list[tuple[int, str, Any]]] = defaultdict(list)  # per group node: (frame, port, message)
        index = 0

        def step(key: str, fn: Any, *a: Any) -> Any:
            t = time.perf_counter()
            out = fn(*a)
            costs[key].append((time.perf_counter() - t) * 1e6)
            if (node := key.split(":")[0]) in group:
                work[node][index] += costs[key][-1]
            return out

        # as a worker does once its nodes are set up (runtime.worker): what exists now is kept out of the collector's
        # full passes, which would otherwise stop a frame for tens of milliseconds now and then
        gc.freeze()
        start_s = time.perf_counter()
        for index in range(frames):
            if args.paced and (wait := start_s + index / args.rate - time.perf_counter()) > 0:
                time.sleep(wait)
            sent.clear()
            step("tracker: simulate", nodes["tracker"].emit, index)
            queue = [(n, p, m) for n, p, m in sent if not (n == "tracker" and p == "truth")]
            sent.clear()
            while queue:
                src, out, message = queue.pop(0)
                # a node in another process with a sampled input is sent only the sampled copy's frames
                targets = [(n, p) for n, p in links[(src, out)]
                           if not isinstance(message, MarkerFrame) or in_copy(message.frame, message.rate)
                           or n in group and src in group or nodes[n].inputs[p].queue != "sampled"]
                crosses = [n for n, _ in targets if n not in group or src not in group]
                if crosses and isinstance(message, MarkerFrame):  # frames that leave a process
                    payload = step(f"{src}: encode {out}", encode, message)
                    for target in crosses:
                        step(f"{target}: decode", decode, payload, MarkerFrame)
                if src == "joints" and skeleton_at is None:
                    skeleton_at = index
                for target, port in targets:
                    if target in group:
                        given[target].append((index, port, message))
                    label = f"{target}: {port}" if port != "markers" else target
                    step(label, nodes[target].process, port, message)
                    queue.extend(sent)
                    sent.clear()
        nodes["recorder"].finish()
        start = skeleton_at if skeleton_at is not None else 0
        graph["recorder"]["config"]["path"] = str(Path(tmp) / "alone.c3d")
        alone = {name: _alone(build(name, lambda port, msg: None), given[name], start, frames)
                 for name in sorted(group, key=list(graph).index)}
    print(f"quickstart frame path at {args.rate:g} Hz{', paced' if args.paced else ''}: {frames} frames, skeleton "
          f"model from frame {skeleton_at}; "
          f"wall-clock us per call since (p50 / p99), and per frame (all its calls' time over the frames)")
    path = total = 0.0
    counted = frames - start
    for key, values in costs.items():
        node = key.split(":")[0]
        where = "frame group" if node in group else "own process"
        per_frame = len(values) >= counted
        tail = np.asarray(values[-counted:] if per_frame else values)
        p50, p99 = np.percentile(tail, [50, 99])
        share = tail.sum() / (counted if per_frame else frames)
        if where == "frame group":
            total += share
            path += p50 if per_frame else 0.0
        print(f"  {key:<28} {where:<12} {p50:8.0f} {p99:8.0f} {share:8.1f}"
              + ("" if per_frame else f"   ({len(values)} calls)"))
    print(f"  frame group, sum of p50 per frame: {path:.0f} us; all its work per frame: {total:.0f} us "
          f"(one frame every {1e6 / args.rate:.0f} us)")
    per_second = int(args.rate)
    print("the frame group's work per frame, us, by second of capture ('*': the skeleton model arrived then)")
    print("  second " + " ".join(f"{node:>9}" for node in work) + "      all")
    for first in range(0, frames, per_second):
        row = [float(w[first:first + per_second].mean()) for w in work.values()]
        mark = "*" if skeleton_at is not None and first <= skeleton_at < first + per_second else " "
        print(f"  {first // per_second:5d}{mark} " + " ".join(f"{v:9.0f}" for v in row) + f" {sum(row):8.0f}")
    print("each node of the frame group alone (its inputs of the run handed to a new node, nothing else in between): "
          "us per frame since the skeleton model, alone and in the group")
    for name, cost in alone.items():
        shared = float(work[name][start:].mean())
        print(f"  {name:<10} alone {cost:7.1f}   in the group {shared:7.1f}   ({shared / cost:.1f} x)")
    print(f"  {'all':<10} alone {sum(alone.values()):7.1f}   in the group "
          f"{sum(float(w[start:].mean()) for w in work.values()):7.1f}")


def _alone(node: Any, inputs: list[tuple[int, str, Any]], start: int, frames: int) -> float:
    """A group node's own cost: the mean time per frame, over the frames from ``start``, of handing a new ``node`` the
    ``inputs`` (frame, port, message) the run gave its namesake (a source: of making each frame), one after the
    other."""
    gc.freeze()  # the run's messages, kept for this, out of the collector's sight as the run's own objects were
    spent = np.zeros(frames)
    if node.is_source():
        for index in range(frames):
            t = time.perf_counter()
            node.emit(index)
            spent[index] = time.perf_counter() - t
    for index, port, message in inputs:
        t = time.perf_counter()
        node.process(port, message)
        spent[index] += time.perf_counter() - t
    node.finish()
    return float(spent[start:].mean() * 1e6)

if __name__ == "__main__":
    main()
