"""One node, one process, one Zenoh session.

The worker subscribes to the node's inputs, hands each message to the node on a single thread (so a node never needs
locks), paces sources in real time, publishes statistics, holds a liveliness token while alive, and ends the node
cleanly on end of stream or SIGTERM.

End of stream is a Zenoh DELETE sample on a data key: a source sends it when it has no more frames, and a node sends
it on its own outputs once every data input it waits for has ended (``graph.end_inputs``: all linked data inputs
but feedback), so a finite run drains in order and stops by itself. Every sample carries its publisher's identity;
what a data input accepts (from whom, which frame numbers, how many markers) is ``mocapflow.runtime.integrity``.

Exit codes: 0 finished; 2 configuration error (never restarted); 3 the node's ``finish()`` failed, so what it was to
write is lost (never restarted: its stream has ended); anything else is a crash the supervisor may restart.
"""

from __future__ import annotations

import argparse
import ctypes
import logging
import os
import signal
import sys
import threading
import time
from collections import deque
from typing import Any

import numpy as np
import zenoh
import zenoh.ext as zext
from pydantic import BaseModel, Field, ValidationError

from mocapflow.messages import DecodeError, Message, NodeStats, decode, encode
from mocapflow.runtime import keys
from mocapflow.runtime.inbox import DEFAULT_CAPACITY, Entry, Inbox, QueuePolicy
from mocapflow.runtime.integrity import InputGuard, Refused, StreamLimits, new_identity
from mocapflow.runtime.node import RUN_ENV, Node
from mocapflow.runtime.plugins import PluginNotFound, load
from mocapflow.runtime.security import SecurityError
from mocapflow.runtime.session import open_client
from mocapflow.runtime.signals import stop_on_signals

EXIT_CONFIG = 2
EXIT_FINISH = 3
STATS_PERIOD_S = 0.5
PEER_WAIT_S = 20.0
MAX_BATCH = 256

log = logging.getLogger("mocapflow.worker")


class WorkerSpec(BaseModel):
    """Everything a worker process needs, resolved by the launcher or an agent from the graph."""

    node: str
    plugin: str
    config: dict[str, Any] = Field(default_factory=dict)
    prefix: str
    inputs: dict[str, str] = Field(default_factory=dict, description="input port -> key expression")
    connect: list[str] = Field(default_factory=list)
    peers: list[str] = Field(default_factory=list, description="nodes a source waits for before emitting")
    end_inputs: list[str] | None = Field(
        default=None, description="inputs whose end of stream ends the node (default: its required data inputs)"
    )
    clock_origin_ns: int | None = Field(
        default=None, description="sources: wall-clock time of frame 0, given when resuming after a restart"
    )
    security: str | None = Field(
        default=None, description="security settings file (TLS, login); its path, so no password is on a command line"
    )
    limits: StreamLimits = Field(default_factory=StreamLimits, description="what the data inputs accept")
    queue: dict[str, QueuePolicy] = Field(default_factory=dict, description="input port -> policy (default 'all')")
    queue_size: int = Field(default=DEFAULT_CAPACITY, ge=1, description="messages an 'all' inbox holds at most")
    run: str = Field(default="", description="the launch this node belongs to (the same across its restarts)")


class Stats:
    """Counters and a latency window; latency is measured from the tracker's capture timestamp."""

    def __init__(self) -> None:
        self.frames_in = 0
        self.frames_out = 0
        self.handled = 0
        self.drops = 0
        self.errors = 0
        self.refused = 0
        self.last_error: str | None = None
        self.latencies_ms: deque[float] = deque(maxlen=4096)
        self._rate_mark = (time.monotonic(), 0)
        self._first_done: float | None = None
        self._last_done = 0.0
        self.rate_hz = 0.0

    def frame_done(self, capture_ns: int) -> None:
        self.handled += 1
        self._last_done = time.monotonic()
        if self._first_done is None:
            self._first_done = self._last_done
        self.latencies_ms.append((time.time_ns() - capture_ns) / 1e6)

    def snapshot(self, node: str, state: str, inbox: Inbox[Any] | None = None) -> NodeStats:
        now = time.monotonic()
        t0, n0 = self._rate_mark
        if state in ("finished", "stopping") and self._first_done is not None and self.handled > 1:
            self.rate_hz = (self.handled - 1) / max(self._last_done - self._first_done, 1e-9)  # whole-run mean
        elif now - t0 > 0:
            self.rate_hz = (self.handled - n0) / (now - t0)
        self._rate_mark = (now, self.handled)
        p50 = p99 = None
        if self.latencies_ms:
            p50, p99 = (float(v) for v in np.percentile(np.fromiter(self.latencies_ms, float), [50, 99]))
        backlog, backlog_ms = inbox.backlog() if inbox is not None else (0, 0.0)
        return NodeStats(
            node=node, pid=os.getpid(), state=state, frames_in=self.frames_in, frames_out=self.frames_out,
            rate_hz=round(self.rate_hz, 2), latency_p50_ms=p50, latency_p99_ms=p99,
            drops=self.drops + (inbox.drops if inbox is not None else 0),
            skipped=inbox.skipped if inbox is not None else 0, backlog=backlog, backlog_ms=round(backlog_ms, 3),
            backlog_max=inbox.max_backlog_frames if inbox is not None else 0,
            backlog_max_ms=round(inbox.max_backlog_ms, 3) if inbox is not None else 0.0,
            errors=self.errors, refused=self.refused, last_error=self.last_error,
        )


class Worker:
    def __init__(self, spec: WorkerSpec, node_cls: type[Node], config: BaseModel, session: zenoh.Session) -> None:
        self.spec = spec
        self.session = session
        self.stats = Stats()
        self.state = "starting"
        self.stop_event = threading.Event()
        self.finished_ok = True
        self.inbox: Inbox[zenoh.Sample] = Inbox(spec.queue_size, {p for p, q in spec.queue.items() if q == "latest"})
        self._publishers: dict[str, Any] = {}
        self._last_frame: dict[str, int] = {}
        self._last_capture_ns: int | None = None
        self.clock_origin_ns: int | None = None
        self.identity = new_identity(spec.node)
        self.guards = {
            port: InputGuard(upstream=key.rsplit("/", 2)[-2], limits=spec.limits)
            for port, key in spec.inputs.items() if port in node_cls.inputs and not node_cls.inputs[port].state
        }
        for port, out in node_cls.outputs.items():
            key = keys.output_key(spec.prefix, spec.node, port)
            enc = zenoh.Encoding(out.type.encoding())
            if out.state:
                self._publishers[port] = zext.declare_advanced_publisher(
                    session, key, encoding=enc, cache=zext.CacheConfig(max_samples=1), publisher_detection=True
                )
            else:
                self._publishers[port] = session.declare_publisher(
                    key, encoding=enc, congestion_control=zenoh.CongestionControl.BLOCK
                )
        self.node = node_cls(config, self._publish, spec.node)
        self._subscribers = [self._subscribe(port, key) for port, key in spec.inputs.items()]
        self._open_inputs = set(spec.end_inputs) if spec.end_inputs is not None else {
            p for p, i in node_cls.inputs.items() if i.required and not i.state and p in spec.inputs
        }
        self._stats_pub = session.declare_publisher(
            keys.stats_key(spec.prefix, spec.node), encoding=zenoh.Encoding(NodeStats.encoding())
        )
        self._token = session.liveliness().declare_token(keys.alive_key(spec.prefix, spec.node))

    # -- plumbing -------------------------------------------------------------------------------------------------
    def _subscribe(self, port: str, key: str) -> Any:
        spec = self.node.inputs[port]

        def on_sample(sample: zenoh.Sample) -> None:
            self.inbox.put(port, sample, end=sample.kind == zenoh.SampleKind.DELETE)

        if spec.state:
            return zext.declare_advanced_subscriber(
                self.session, key, on_sample,
                history=zext.HistoryConfig(detect_late_publishers=True, max_samples=1),
            )
        return self.session.declare_subscriber(key, on_sample)

    def _publish(self, port: str, message: Message) -> None:
        if port not in self._publishers:
            raise KeyError(f"node {self.spec.node!r} has no output {port!r}")
        self._publishers[port].put(encode(message), attachment=self.identity)
        self.stats.frames_out += 1
        self._last_capture_ns = message.capture_ns

    def _end_outputs(self) -> None:
        for port, pub in self._publishers.items():
            if not self.node.outputs[port].state:
                pub.delete(attachment=self.identity)

    def _report_error(self, where: str, exc: BaseException) -> None:
        self.stats.errors += 1
        self.stats.last_error = f"{where}: {exc}"
        if self.stats.errors <= 3:
            log.error("%s: %s", where, exc, exc_info=not isinstance(exc, (DecodeError, ValueError)))
        elif self.stats.errors in (4, 100, 10_000):
            log.error("%s: %s (%d errors so far; further ones counted in stats)", where, exc, self.stats.errors)

    def _stats_loop(self) -> None:
        while not self.stop_event.wait(STATS_PERIOD_S):
            self.publish_stats()

    def publish_stats(self) -> None:
        stats = self.stats.snapshot(self.spec.node, self.state, self.inbox)
        stats.clock_origin_ns = self.clock_origin_ns
        self._stats_pub.put(encode(stats))

    # -- running --------------------------------------------------------------------------------------------------
    def run(self) -> None:
        threading.Thread(target=self._stats_loop, name="stats", daemon=True).start()
        try:
            if self.node.is_source():
                self._wait_for_peers()
                self.state = "running"
                self._run_source()
            else:
                self.state = "running"
                self._run_sink()
        finally:
            self.state = "finished" if not self.stop_event.is_set() else "stopping"
            try:
                self.finished_ok = self._finish()
            finally:
                self.publish_stats()
                self.stop_event.set()

    def _finish(self) -> bool:
        """The node's ``finish()``; its failure is reported, never a crash to restart (the stream has ended)."""
        try:
            self.node.finish()
        except Exception as exc:
            self.stats.errors += 1
            self.stats.last_error = f"finish: {exc}"
            log.error("node %s: finish failed, its output is lost: %s", self.spec.node, exc)
            return False
        return True

    def _wait_for_peers(self) -> None:
        """Sources wait for every other node's liveliness token so that no first frame goes unheard."""
        wanted = set(self.spec.peers) - {self.spec.node}
        deadline = time.monotonic() + PEER_WAIT_S
        while wanted and not self.stop_event.is_set():
            replies = self.session.liveliness().get(keys.alive_key(self.spec.prefix), timeout=1.0)
            seen = {str(r.ok.key_expr).rsplit("/", 1)[-1] for r in replies if r.ok is not None}
            wanted -= seen
            if not wanted:
                return
            if time.monotonic() > deadline:
                log.warning("starting without nodes %s: not alive after %.0f s", sorted(wanted), PEER_WAIT_S)
                return
            time.sleep(0.05)

    def _run_source(self) -> None:
        period = 1.0 / self.node.rate
        origin_ns = self.spec.clock_origin_ns or time.time_ns()
        self.clock_origin_ns = origin_ns
        self.publish_stats()
        index = self.node.first_index(max(0.0, (time.time_ns() - origin_ns) / 1e9))
        # Pace against the source's clock: frame i is due at origin + i * period, so a restarted source resumes on
        # schedule and a late frame is caught up at once instead of shifting every later frame.
        t0 = time.monotonic() - (time.time_ns() - origin_ns) / 1e9
        while not self.stop_event.is_set():
            delay = t0 + index * period - time.monotonic()
            if delay > 0 and self.node.paced:
                self.stop_event.wait(delay)
                if self.stop_event.is_set():
                    break
            sent = self.stats.frames_out
            if not self.node.emit(index):
                break
            if self._last_capture_ns is not None and self.stats.frames_out > sent:
                self.stats.frame_done(self._last_capture_ns)
            index += 1
        self._end_outputs()

    def _run_sink(self) -> None:
        pending: Entry[zenoh.Sample] | None = None
        while not self.stop_event.is_set():
            if pending is None:
                pending = self.inbox.get(timeout=0.1)
                if pending is None:
                    continue
            port, sample, skipped = pending.port, pending.item, pending.skipped
            pending = None
            if sample.kind == zenoh.SampleKind.DELETE:
                if port in self.guards and not self.guards[port].accept_end(_identity(sample)):
                    self.stats.refused += 1
                    self._report_error(f"input {port!r}", Refused(
                        f"end of stream from {_who(sample)}, not from the stream's publisher: ignored"))
                    continue
                self._open_inputs.discard(port)
                if not self._open_inputs and not self.node.inputs[port].state:
                    self._end_outputs()
                    return
                continue
            # A node that fell behind catches up on what has queued on this input since, in one batch.
            batch = [(sample, skipped)]
            while len(batch) < MAX_BATCH:
                pending = self.inbox.get(timeout=0)
                if pending is None:
                    break
                if pending.port != port or pending.end:
                    break
                batch.append((pending.item, pending.skipped))
                pending = None
            self._handle(port, batch)

    def _decode(self, port: str, sample: zenoh.Sample, skipped: int = 0) -> Message | None:
        """The message of ``sample``, checked; ``skipped``: how many messages it replaced in a 'latest' inbox (not
        counted again as lost frames)."""
        spec = self.node.inputs[port]
        try:
            message = decode(sample.payload.to_bytes(), spec.type)
        except DecodeError as exc:
            self._report_error(f"input {port!r} ({sample.key_expr})", exc)
            return None
        if not spec.state:
            self.stats.frames_in += 1
            if port in self.guards:
                guard = self.guards[port]
                try:
                    guard.check_source(_identity(sample))
                    message = guard.check_frame(message)
                except Refused as exc:
                    self.stats.refused += 1
                    self._report_error(f"input {port!r} ({_who(sample)})", exc)
                    return None
            last = self._last_frame.get(port)
            if last is not None and message.frame != last + 1:
                if message.frame > last + 1 + skipped:
                    self.stats.drops += message.frame - last - 1 - skipped
                else:
                    self._report_error(f"input {port!r}", ValueError(f"frame {message.frame} after {last}"))
            self._last_frame[port] = message.frame
        return message

    def _handle(self, port: str, samples: list[tuple[zenoh.Sample, int]]) -> None:
        messages = [m for m in (self._decode(port, s, k) for s, k in samples) if m is not None]
        if type(self.node).process_batch is Node.process_batch:
            groups = [[m] for m in messages]  # one at a time, so a bad frame costs only itself
        else:
            groups = [messages] if messages else []
        for group in groups:
            try:
                if len(group) == 1:
                    self.node.process(port, group[0])
                else:
                    self.node.process_batch(port, group)
            except Exception as exc:  # a bad frame must not end the stage: log, count, go on
                self._report_error(f"processing {port!r} frame {group[0].frame}", exc)
                continue
            if not self.node.inputs[port].state:
                for message in group:
                    self.stats.frame_done(message.capture_ns)


def _identity(sample: zenoh.Sample) -> bytes | None:
    return sample.attachment.to_bytes() if sample.attachment is not None else None


def _who(sample: zenoh.Sample) -> str:
    identity = _identity(sample)
    return identity.decode(errors="replace") if identity is not None else "an anonymous publisher"


def _die_with_parent() -> None:
    """Ask Linux to SIGTERM this process if its launcher dies, so no orphan outlives a killed launcher."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def run_worker(spec: WorkerSpec) -> int:
    os.environ[RUN_ENV] = spec.run
    try:
        node_cls = load(spec.plugin)
        config = node_cls.Config.model_validate(spec.config)
        session = open_client(spec.connect, spec.security)
    except (PluginNotFound, ValidationError, SecurityError) as exc:
        log.error("node %s: %s", spec.node, exc)
        return EXIT_CONFIG
    try:
        try:
            worker = Worker(spec, node_cls, config, session)
        except Exception as exc:  # e.g. a file that cannot be opened: a configuration problem, not a crash
            log.error("node %s could not start: %s", spec.node, exc)
            return EXIT_CONFIG
        # From here on a stop request ends the node in order, and once it is done none turns it into one killed by a
        # signal (the interpreter's shutdown included): the handler's predecessor is SIG_IGN.
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        with stop_on_signals(worker.stop_event, (signal.SIGTERM,)):
            worker.run()
        return 0 if worker.finished_ok else EXIT_FINISH
    finally:
        session.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mocapflow-worker", description="run one mocapflow node")
    parser.add_argument("spec", help="WorkerSpec as JSON")
    args = parser.parse_args(argv)
    spec = WorkerSpec.model_validate_json(args.spec)
    logging.basicConfig(
        level=os.environ.get("MOCAPFLOW_LOG", "INFO"), stream=sys.stderr,
        format="%(levelname)s %(message)s",
    )
    # The launcher decides when nodes stop; Ctrl-C in the terminal reaches it, not each node.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent()
    return run_worker(spec)


if __name__ == "__main__":
    sys.exit(main())
