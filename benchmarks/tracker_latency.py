"""Latency each live tracker adapter adds, from the stand-in server's send to the adapter's publish, and the jitter
left by the clock mapping (capture time given to a frame minus the moment the server sent it: at speed 1 the
stand-ins stamp frame i with i / rate), measured as the spread of the offset the mapping applies.

The server runs in this process on its own thread (so that it can note each frame's send time), the adapter node is
driven the way the worker drives a source (``emit`` in a loop) and its ``publish`` notes the time; the Zenoh put that
follows in a real graph is measured by ``mocapflow bench``, not here.

    python benchmarks/tracker_latency.py [FILE] [--seconds S]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.io.markers import MarkerData, read_markers

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "cmu_85_02.c3d"


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def measure(protocol: str, data: MarkerData) -> dict[str, Any]:
    from mocapflow.plugins.natnet import NatNetConfig, NatNetTracker
    from mocapflow.plugins.qtm import QtmConfig, QtmTracker
    from mocapflow.trackers.natnet_server import NatNetServer
    from mocapflow.trackers.qtm_server import QtmServer

    sent: dict[int, int] = {}
    published: dict[int, tuple[int, int]] = {}  # frame -> (publish ns, capture ns)
    port = free_port()
    loop = asyncio.new_event_loop()
    ready = threading.Event()
    record = lambda frame, ns: sent.__setitem__(frame, ns)  # noqa: E731
    server = QtmServer(data, on_sent=record) if protocol == "qtm" else NatNetServer(data, on_sent=record)

    def serve() -> None:
        with contextlib.suppress(asyncio.CancelledError):
            loop.run_until_complete(server.serve("127.0.0.1", port, ready.set))

    async def cancel() -> None:
        for task in asyncio.all_tasks():
            if task is not asyncio.current_task():
                task.cancel()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    ready.wait(10)

    def publish(_port: str, message: Any) -> None:
        published[message.frame] = (time.time_ns(), message.capture_ns)

    if protocol == "qtm":
        node: Any = QtmTracker(QtmConfig(port=port, end_with_capture=True), publish)
    else:
        node = NatNetTracker(NatNetConfig(command_port=port, multicast=False, end_after_s=1.0), publish)
    index = 0
    while node.emit(index):
        index += 1
    node.finish()
    asyncio.run_coroutine_threadsafe(cancel(), loop)
    thread.join(timeout=5)
    frames = sorted(set(sent) & set(published))
    settled = [f for f in frames if f - frames[0] >= data.rate]  # after the first second (start-up, first offsets)
    latency = np.array([(published[f][0] - sent[f]) / 1e6 for f in settled])
    # the offset the clock mapping applies: capture time minus the tracker's own stamp ((frame - first) / rate)
    offset = np.array([published[f][1] / 1e6 - (f - data.first_frame) / data.rate * 1e3 for f in settled])
    return {"frames": len(frames), "sent": len(sent), "latency": latency, "jitter": offset - np.median(offset)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("file", nargs="?", default=str(DEFAULT))
    parser.add_argument("--seconds", type=float, default=6.0, help="length of file to play")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    logging.getLogger("asyncio").setLevel(logging.CRITICAL)  # the servers' tasks are cancelled at the end
    whole = read_markers(args.file)
    n = min(len(whole.positions), int(args.seconds * whole.rate))
    data = MarkerData(whole.positions[:n], whole.labels, whole.rate, whole.first_frame)
    print(f"{Path(args.file).name}: {n} frames x {len(data.labels)} markers at {data.rate:g} Hz, speed 1")
    print("latency and clock jitter over the frames after the first second (ms)")
    print(f"{'adapter':<8}{'frames':>8}{'send->publish p50':>19}{'p99':>8}{'max':>8}"
          f"{'offset - median p1':>20}{'p99':>8}{'max':>8}")
    for protocol in ("qtm", "natnet"):
        r = measure(protocol, data)
        lat, jit = r["latency"], r["jitter"]
        print(f"{protocol:<8}{r['frames']:>5}/{r['sent']:<3}{np.percentile(lat, 50):>18.3f}"
              f"{np.percentile(lat, 99):>8.3f}{lat.max():>8.3f}{np.percentile(jit, 1):>20.3f}"
              f"{np.percentile(jit, 99):>8.3f}{np.abs(jit).max():>8.3f}")


if __name__ == "__main__":
    main()
