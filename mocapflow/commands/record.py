"""``mocapflow record KEY... -o FILE.mcap`` and ``mocapflow replay FILE.mcap`` with the original timing."""

from __future__ import annotations

import argparse
import itertools
import queue
import threading
import time

from mocapflow.commands import timeout_option
from mocapflow.runtime.session import DEFAULT_ENDPOINT
from mocapflow.runtime.signals import stop_on_signals

MIN_SPEED, MAX_SPEED = 1e-3, 1e3


def register(sub: argparse._SubParsersAction) -> None:
    rec = sub.add_parser("record", help="record keys of a live system to an MCAP file")
    rec.add_argument("keys", nargs="+", help="key expressions, e.g. mocapflow/quickstart/** ")
    rec.add_argument("-o", "--output", required=True, help="output .mcap file")
    rec.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    rec.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                     help=f"router to join (default {DEFAULT_ENDPOINT})")
    timeout_option(rec)
    rec.set_defaults(func=_record)

    rep = sub.add_parser("replay", help="publish an MCAP recording again with its original timing")
    rep.add_argument("recording", help=".mcap file written by `mocapflow record`")
    rep.add_argument("--speed", type=float, default=1.0, help="time factor (2 = twice as fast)")
    rep.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                     help=f"router to join (default {DEFAULT_ENDPOINT})")
    timeout_option(rep)
    rep.set_defaults(func=_replay)


def _record(args: argparse.Namespace) -> int:
    import zenoh

    from mocapflow.io.recording import RecordedSample, RecordingWriter
    from mocapflow.runtime import keys
    from mocapflow.runtime.session import open_client, subscribe_with_cache

    inbox: queue.Queue[RecordedSample] = queue.Queue()
    stop = threading.Event()

    asked = {kind for kind in keys.COPIES if any(f"/{kind}" in key for key in args.keys)}

    def on_sample(sample: zenoh.Sample) -> None:
        kind = keys.copy_kind(str(sample.key_expr))
        if kind is not None and kind not in asked:  # copies of the streams (previews, samples), unless asked for
            return
        inbox.put(RecordedSample(key=str(sample.key_expr), encoding=str(sample.encoding),
                                 payload=sample.payload.to_bytes(), log_time_ns=time.time_ns(),
                                 delete=sample.kind == zenoh.SampleKind.DELETE))

    with stop_on_signals(stop):
        deadline = None if args.duration is None else time.monotonic() + args.duration
        with open_client(args.connect, timeout=args.timeout) as session, RecordingWriter(args.output) as writer:
            subs = [subscribe_with_cache(session, key, on_sample) for key in args.keys]  # models too, as nodes get them
            print(f"recording {', '.join(args.keys)} to {args.output} (Ctrl-C to stop)", flush=True)
            flushed = time.monotonic()
            while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
                try:
                    writer.write(inbox.get(timeout=0.1))
                except queue.Empty:
                    pass
                if time.monotonic() - flushed > 0.5:  # a killed recorder keeps all but the last half second
                    writer.flush()
                    flushed = time.monotonic()
            for s in subs:
                s.undeclare()
            while not inbox.empty():
                writer.write(inbox.get_nowait())
            print(f"recorded {writer.count} samples to {args.output}", flush=True)
    return 0


def _replay(args: argparse.Namespace) -> int:
    import numpy as np
    import zenoh

    from mocapflow.errors import MocapflowError
    from mocapflow.io.recording import read_recording
    from mocapflow.runtime.session import open_client

    if not MIN_SPEED <= args.speed <= MAX_SPEED:
        raise MocapflowError(f"--speed {args.speed:g}: must be between {MIN_SPEED:g} and {MAX_SPEED:g}")
    samples = read_recording(args.recording)
    first = next(samples, None)
    if first is None:
        print(f"{args.recording}: empty recording")
        return 0
    stop = threading.Event()
    with stop_on_signals(stop):
        count = 0
        late_ms: list[float] = []
        with open_client(args.connect, timeout=args.timeout) as session:
            publishers: dict[tuple[str, str], zenoh.Publisher] = {}
            t0 = time.monotonic()
            for sample in itertools.chain([first], samples):
                due = t0 + (sample.log_time_ns - first.log_time_ns) / 1e9 / args.speed
                while (delay := due - time.monotonic()) > 0 and not stop.is_set():
                    time.sleep(delay if delay > 0.002 else 0)  # sleep coarsely, then spin for the last 2 ms
                if stop.is_set():
                    break
                ident = (sample.key, sample.encoding)
                if ident not in publishers:
                    publishers[ident] = session.declare_publisher(sample.key, encoding=zenoh.Encoding(sample.encoding),
                                                                  congestion_control=zenoh.CongestionControl.BLOCK)
                if sample.delete:
                    publishers[ident].delete()
                else:
                    publishers[ident].put(sample.payload)
                late_ms.append((time.monotonic() - due) * 1e3)
                count += 1
    p50, p95 = np.percentile(late_ms, [50, 95]) if late_ms else (0.0, 0.0)
    print(f"replayed {count} samples from {args.recording}; sent after their due time by p50 {p50:.3f} ms,"
          f" p95 {p95:.3f} ms, max {max(late_ms, default=0):.3f} ms")
    return 0
