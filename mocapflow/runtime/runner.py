"""Running one node, whatever carries its messages: frame order, batches, end of stream, statistics, errors.

The Zenoh adapter (``mocapflow.runtime.worker``) decodes and checks what arrives from other processes and hands the
messages here; inside a node group the messages of the other members come here as Python objects, in order, with no
encode. Either way the node sees the same calls, so a graph gives the same result grouped or not.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np
from pydantic import BaseModel

from mocapflow.messages import DecodeError, Message, NodeStats
from mocapflow.runtime.node import Node

log = logging.getLogger("mocapflow.worker")


RECENT = 4096
"""How many of the latest frames the live latency figures cover (a few seconds at a tracker's rate)."""
_FLOOR_MS = 1e-3
_STEP = math.log(1.01)
_BINS = int(math.log(1e7 / _FLOOR_MS) / _STEP) + 1  # magnitudes from a microsecond to about three hours


class LatencyHistogram:
    """Every latency of a run, in bins 1 % wide, for percentiles over the whole run at a fixed cost a frame and in
    fixed memory. Signed: across machines the tracker's clock and this one's may disagree by more than a latency."""

    def __init__(self) -> None:
        self.counts = [0] * (2 * _BINS + 1)  # bin _BINS: under a microsecond either way; above it positive values

    def add(self, ms: float) -> None:
        size = abs(ms)
        k = 0 if not size >= _FLOOR_MS else min(int(math.log(size / _FLOOR_MS) / _STEP) + 1, _BINS)
        self.counts[_BINS + k if ms > 0 else _BINS - k] += 1

    def percentiles(self, qs: list[float]) -> list[float] | None:
        """The value at each percentile in ``qs`` (to within 1 %, or a microsecond), None before any value."""
        cum = np.cumsum(self.counts)
        if cum[-1] == 0:
            return None
        rank = np.maximum(np.ceil(np.asarray(qs) / 100 * cum[-1]), 1)
        k = np.searchsorted(cum, rank) - _BINS
        size = np.where(k == 0, 0.0, _FLOOR_MS * np.exp((np.abs(k) - 0.5) * _STEP))  # a bin's middle
        return [float(v) for v in np.sign(k) * size]


class Stats:
    """Counters and latency; latency is measured from the tracker's capture timestamp, over the latest ``RECENT``
    frames while the node runs and over the whole run once it has ended."""

    def __init__(self) -> None:
        self.frames_in = 0
        self.frames_out = 0
        self.handled = 0
        self.drops = 0
        self.errors = 0
        self.refused = 0
        self.unpaired = 0
        self.passed = 0  # passed over: the node did not want them (``Node.wanted``), or a stream's copy left them out
        self.last_error: str | None = None
        self.latencies_ms: deque[float] = deque(maxlen=RECENT)
        self.run_latency = LatencyHistogram()
        self._rate_mark = (time.monotonic(), 0)
        self._first_done: float | None = None
        self._last_done = 0.0
        self.rate_hz = 0.0

    def frame_done(self, capture_ns: int) -> None:
        self.handled += 1
        self._last_done = time.monotonic()
        if self._first_done is None:
            self._first_done = self._last_done
        latency = (time.time_ns() - capture_ns) / 1e6
        self.latencies_ms.append(latency)
        self.run_latency.add(latency)

    def snapshot(self, node: str, state: str, **inbox: Any) -> NodeStats:
        """``inbox``: the node's inbox figures (``drops`` refused, ``skipped``, ``backlog``...)."""
        now = time.monotonic()
        t0, n0 = self._rate_mark
        if state in ("finished", "stopping") and self._first_done is not None and self.handled > 1:
            self.rate_hz = (self.handled - 1) / max(self._last_done - self._first_done, 1e-9)  # whole-run mean
        elif now - t0 > 0:
            self.rate_hz = (self.handled - n0) / (now - t0)
        self._rate_mark = (now, self.handled)
        p50 = p99 = None
        if state in ("finished", "stopping", "failed"):
            p50, p99 = self.run_latency.percentiles([50, 99]) or (None, None)
        elif self.latencies_ms:
            p50, p99 = (float(v) for v in np.percentile(np.fromiter(self.latencies_ms, float), [50, 99]))
        return NodeStats(
            node=node, pid=os.getpid(), state=state, frames_in=self.frames_in, frames_out=self.frames_out,
            rate_hz=round(self.rate_hz, 2), latency_p50_ms=p50, latency_p99_ms=p99,
            errors=self.errors, refused=self.refused, unpaired=self.unpaired, last_error=self.last_error,
            **{**inbox, "drops": self.drops + inbox.get("drops", 0),
               "skipped": self.passed + inbox.get("skipped", 0)},
        )


class Runner:
    """One node and its bookkeeping. ``send(port, message)`` carries what the node publishes; ``end_inputs`` are the
    data inputs whose end of stream ends the node; ``linked`` the inputs the graph links (None: no graph)."""

    def __init__(self, name: str, node_cls: type[Node], config: BaseModel, send: Callable[[str, Message], None],
                 end_inputs: set[str], linked: set[str] | None = None) -> None:
        self.name = name
        self.stats = Stats()
        self.ended = False
        self.failed = False  # its finish() failed: what it was to write is lost
        self._send = send
        self._last_frame: dict[str, int] = {}
        self._passed: dict[str, int] = {}  # per data input: messages passed over since the last one counted in
        self._last_capture_ns: int | None = None
        self._open_inputs = set(end_inputs)
        self.ended_inputs: set[str] = set()
        self.node = node_cls(config, self._publish, name)
        self.node.linked = None if linked is None else frozenset(linked)

    def _publish(self, port: str, message: Message) -> None:
        if port not in self.node.outputs:
            raise KeyError(f"node {self.name!r} has no output {port!r}")
        self._send(port, message)
        self.stats.frames_out += 1
        self._last_capture_ns = message.capture_ns

    def report_error(self, where: str, exc: BaseException) -> None:
        self.stats.errors += 1
        self.stats.last_error = f"{where}: {exc}"
        if self.stats.errors <= 3:
            log.error("%s: %s", where, exc, exc_info=not isinstance(exc, (DecodeError, ValueError)))
        elif self.stats.errors in (4, 100, 10_000):
            log.error("%s: %s (%d errors so far; further ones counted in stats)", where, exc, self.stats.errors)

    def wants(self, port: str, skipped: int = 0) -> bool:
        """Whether the node wants the next message on ``port`` (``Node.wanted``; state inputs always): one it does
        not want is passed over, counted as skipped, with the ``skipped`` ones the inbox passed over before it."""
        if self.node.inputs[port].state:
            return True
        try:
            if self.node.wanted(port):
                return True
        except Exception as exc:  # a faulty sampling rule costs nothing but its own report: the message is handled
            self.report_error(f"input {port!r}: wanted()", exc)
            return True
        self.stats.passed += 1
        self._passed[port] = self._passed.get(port, 0) + 1 + skipped
        return False

    def take_back(self, port: str) -> None:
        """The message on ``port`` last passed over (``wants`` said no) is handed over after all: not skipped."""
        self.stats.passed -= 1
        self._passed[port] -= 1

    def thinned(self, port: str, frame: int, skipped: int, stride: int | None = None) -> int:
        """The frames before ``frame`` that a copy of the stream on ``port`` left out (``skipped`` of them replaced
        in the inbox, counted there): counted as passed over, not lost. A preview may leave out any frame; a sampled
        copy (``stride``) only those whose number is not a multiple of its stride, so a missing multiple is a loss.
        Returns the frames left out, skipped included."""
        last = self._last_frame.get(port)
        gap = 0 if last is None else max(0, frame - last - 1)
        if stride is not None and last is not None and gap:
            gap -= (frame - 1) // stride - last // stride  # the samples between: those the copy was to carry
        self.stats.passed += max(0, gap - skipped)
        return max(gap, skipped)

    def count_in(self, port: str, message: Message, skipped: int = 0) -> None:
        """Count a data message and check its frame number follows the last one on ``port``; ``skipped``: messages
        of that input the inbox passed over just before it (counted there, not again as lost frames), to which
        those the node did not want are added."""
        skipped += self._passed.pop(port, 0)
        self.stats.frames_in += 1
        last = self._last_frame.get(port)
        if last is not None and message.frame != last + 1:
            if message.frame > last + 1 + skipped:
                self.stats.drops += message.frame - last - 1 - skipped
            elif message.frame <= last:
                self.report_error(f"input {port!r}", ValueError(f"frame {message.frame} after {last}"))
        self._last_frame[port] = message.frame

    def last_frame(self, port: str) -> int:
        """The frame number last received on data input ``port``; -1 before any."""
        return self._last_frame.get(port, -1)

    def handle(self, port: str, messages: list[Message]) -> None:
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
                self.report_error(f"processing {port!r} frame {getattr(group[0], 'frame', '-')}", exc)
                continue
            if not self.node.inputs[port].state:
                for message in group:
                    self.stats.frame_done(message.capture_ns)

    def end_of(self, port: str) -> bool:
        """Input ``port`` has ended; True when that ends the node (every input it waits for has ended)."""
        self._open_inputs.discard(port)
        self.ended_inputs.add(port)
        if self.ended or self._open_inputs or self.node.inputs[port].state:
            return False
        self.ended = True
        return True

    def emit(self, index: int) -> bool:
        """Sources: produce frame ``index``; False (and the node ends) when the source has no more frames."""
        sent = self.stats.frames_out
        if not self.node.emit(index):
            self.ended = True
            return False
        if self._last_capture_ns is not None and self.stats.frames_out > sent:
            self.stats.frame_done(self._last_capture_ns)
        return True

    def prepare(self, index: int) -> None:
        """Sources: the node's ``prepare(index)``; its failure is reported and costs nothing else (``emit`` does
        without it)."""
        try:
            self.node.prepare(index)
        except Exception as exc:
            self.report_error(f"prepare frame {index}", exc)

    def finish(self) -> bool:
        """The node's ``finish()``; its failure is reported, never a crash to restart (the stream has ended)."""
        try:
            self.node.finish()
        except Exception as exc:
            self.stats.errors += 1
            self.stats.last_error = f"finish: {exc}"
            log.error("node %s: finish failed, its output is lost: %s", self.name, exc)
            self.failed = True
            return False
        return True
