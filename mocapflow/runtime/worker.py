"""One process, one Zenoh session, one node or a node group.

The worker subscribes to its nodes' inputs, hands each message to its node (``mocapflow.runtime.runner``) on a single
thread (so a node never needs locks), paces sources in real time, publishes statistics, holds a liveliness token per
node while alive, and ends the nodes cleanly on end of stream or SIGTERM.

A node group runs several nodes in this one process: what one member publishes for another is handed over as the
Python object, in order, on the same thread, before anything else arrives from outside (so a feedback loop inside a
group never races: the filler's prediction reaches the labeller before the tracker's next frame). Every output is still
published on its key for outside subscribers: always when a node of the graph outside the group reads it whole
(``Graph.linked_outputs``), otherwise only while Zenoh reports a matching subscriber (a viewer, ``mocapflow echo``), so
nobody's frames are encoded for no one.

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
import gc
import logging
import os
import signal
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import zenoh
import zenoh.ext as zext
from pydantic import BaseModel, Field, ValidationError

from mocapflow.messages import DecodeError, Message, NodeStats, decode, encode
from mocapflow.runtime import keys
from mocapflow.runtime.cpus import REALTIME_PRIORITY, CpuPolicy
from mocapflow.runtime.inbox import DEFAULT_CAPACITY, Entry, Inbox, QueuePolicy
from mocapflow.runtime.integrity import InputGuard, Refused, StreamLimits, new_identity
from mocapflow.runtime.node import RUN_ENV, Node
from mocapflow.runtime.plugins import PluginNotFound, load
from mocapflow.runtime.preview import Preview
from mocapflow.runtime.runner import Runner
from mocapflow.runtime.sampling import base_stride, in_copy
from mocapflow.runtime.security import SecurityError
from mocapflow.runtime.session import open_client, subscribe_with_cache
from mocapflow.runtime.signals import stop_on_signals

EXIT_CONFIG = 2
EXIT_FINISH = 3
STATS_PERIOD_S = 0.5
PEER_WAIT_S = 20.0
MAX_BATCH = 256
QUIET_S = 1.0  # an input silent this long may have ended before this process listened: the launcher is asked

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
    queue: dict[str, QueuePolicy] = Field(default_factory=dict,
                                          description="input port -> policy (default: the plugin's)")
    queue_size: int = Field(default=DEFAULT_CAPACITY, ge=1, description="messages an 'all' inbox holds at most")
    nice: int = Field(default=0, ge=0, le=19, description="CPU niceness of the process")
    cpu: CpuPolicy = Field(default="shared", description="'own': asks for a CPU core of its own; 'idle': runs on "
                           "CPU time no other process wants; 'realtime': runs at a real-time priority")
    cpus: list[int] | None = Field(default=None, description="the CPU cores the process runs on, as the launcher or "
                                   "agent that starts it assigned them; none: wherever it was started")
    wait_for: dict[str, float] = Field(
        default_factory=dict, description="input port -> ms: how long a frame waits for that input's message of the "
        "same frame number (feedback from another process)")
    linked: list[str] | None = Field(
        default=None, description="outputs that nodes in other processes read whole (always published); the "
        "others only while someone subscribes. None: publish every output")
    members: list[WorkerSpec] = Field(
        default_factory=list, description="a node group: the nodes this process runs (``node`` names the group)")

    def nodes(self) -> list[WorkerSpec]:
        """The node specs this process runs: the group's members, or this one node."""
        return self.members or [self]
    run: str = Field(default="", description="the launch this node belongs to (the same across its restarts)")



END = object()
"""Handed over inside a group in place of a message: that output has ended."""


@dataclass
class Member:
    """One node of this process, with its Zenoh side: publishers, input guards, statistics key, liveliness token."""

    spec: WorkerSpec
    publishers: dict[str, Any]
    identity: bytes
    guards: dict[str, InputGuard]
    routes: dict[str, list[tuple[Member, str]]] = field(default_factory=dict)  # output -> members' inputs it feeds
    internal: set[str] = field(default_factory=set)  # inputs fed by another member
    wanted: dict[str, bool] = field(default_factory=dict)  # output -> published on Zenoh now
    preview_publishers: dict[str, Any] = field(default_factory=dict)  # output -> publisher of its preview
    models: set[str] = field(default_factory=set)  # outputs that carry models (state)
    previews: dict[str, Preview[Message]] = field(default_factory=dict)  # data output -> its preview, while watched
    sampled_publishers: dict[str, Any] = field(default_factory=dict)  # data output -> publisher of its sampled copy
    sampling: set[str] = field(default_factory=set)  # data outputs whose sampled copy someone subscribes to
    latest: set[str] = field(default_factory=set)  # inputs whose policy is 'latest' or 'preview'
    previewed: set[str] = field(default_factory=set)  # inputs whose policy is 'preview'
    sampled: set[str] = field(default_factory=set)  # inputs whose policy is 'sampled'
    held: dict[str, Any] = field(default_factory=dict)  # latest input -> newest message passed over (maybe undecoded)
    listeners: list[Any] = field(default_factory=list)
    stats_pub: Any = None
    token: Any = None
    runner: Runner = field(init=False)

    @property
    def name(self) -> str:
        return self.spec.node

    def listened(self, port: str) -> bool:
        """Whether a message on output ``port`` would reach anyone now: a member of the group, or Zenoh (the
        output itself, its sampled copy or its preview)."""
        return bool(self.routes.get(port)) or self.wanted[port] or port in self.sampling or port in self.previews


class Worker:
    def __init__(self, spec: WorkerSpec, classes: dict[str, type[Node]], configs: dict[str, BaseModel],
                 session: zenoh.Session) -> None:
        self.spec = spec
        self.session = session
        self.state = "starting"
        self.stop_event = threading.Event()
        self.finished_ok = True
        self.clock_origin_ns: int | None = None
        self._local: deque[tuple[Member, str, Any]] = deque()  # hand-overs inside the group, in order
        self._deferred: deque[Entry[zenoh.Sample]] = deque()  # from outside, set aside while waiting for feedback
        self._heard = self._asked = time.monotonic()  # when something last came from outside; when ``_ask_ended`` ran
        self._finished: deque[str] = deque()  # nodes the launcher says have finished (filled by its replies)
        self.members: dict[str, Member] = {}
        for node in spec.nodes():
            self.members[node.node] = self._member(node, classes[node.node], configs[node.node])
        self.inbox: Inbox[zenoh.Sample] = Inbox(
            spec.queue_size, {f"{m.name}/{port}" for m in self.members.values() for port in m.latest})
        by_key = {keys.output_key(m.spec.prefix, m.name, port): (m, port)
                  for m in self.members.values() for port in m.runner.node.outputs}
        self._subscribers = []
        for m in self.members.values():
            for port, key in m.spec.inputs.items():
                if key in by_key:
                    src, out = by_key[key]
                    src.routes.setdefault(out, []).append((m, port))
                    m.internal.add(port)
                else:
                    self._subscribers.append(self._subscribe(m, port, key))
        for m in self.members.values():
            m.stats_pub = session.declare_publisher(
                keys.stats_key(m.spec.prefix, m.name), encoding=zenoh.Encoding(NodeStats.encoding()))
            m.token = session.liveliness().declare_token(keys.alive_key(m.spec.prefix, m.name))
        sources = [m for m in self.members.values() if m.runner.node.is_source()]
        if len(sources) > 1:
            raise ValueError(f"a node group runs one source at most, not {', '.join(m.name for m in sources)}")
        self.source = sources[0] if sources else None

    def _member(self, spec: WorkerSpec, node_cls: type[Node], config: BaseModel) -> Member:
        publishers: dict[str, Any] = {}
        for port, out in node_cls.outputs.items():
            key = keys.output_key(spec.prefix, spec.node, port)
            enc = zenoh.Encoding(out.type.encoding())
            if out.state:
                publishers[port] = zext.declare_advanced_publisher(
                    self.session, key, encoding=enc, cache=zext.CacheConfig(max_samples=1), publisher_detection=True
                )
            else:
                publishers[port] = self.session.declare_publisher(
                    key, encoding=enc, congestion_control=zenoh.CongestionControl.BLOCK
                )
        ends = set(spec.end_inputs) if spec.end_inputs is not None else {
            p for p, i in node_cls.inputs.items() if i.required and not i.state and p in spec.inputs
        }
        policy = {p: spec.queue.get(p, i.queue) for p, i in node_cls.inputs.items()}
        member = Member(spec=spec, publishers=publishers, identity=new_identity(spec.node),
                        models={p for p, out in node_cls.outputs.items() if out.state},
                        latest={p for p, q in policy.items() if q in ("latest", "preview")},
                        previewed={p for p, q in policy.items() if q == "preview"},
                        sampled={p for p, q in policy.items() if q == "sampled"},
                        guards={port: InputGuard(upstream=key.rsplit("/", 2)[-2], limits=spec.limits)
                                for port, key in spec.inputs.items()
                                if port in node_cls.inputs and not node_cls.inputs[port].state})
        for port, out in node_cls.outputs.items():
            member.wanted[port] = out.state or spec.linked is None or port in spec.linked
            if not member.wanted[port]:
                def on_matching(status: zenoh.MatchingStatus, port: str = port) -> None:
                    member.wanted[port] = status.matching
                member.listeners.append(publishers[port].declare_matching_listener(on_matching))
                member.wanted[port] = publishers[port].matching_status.matching
            self._preview(member, port, out.state, out.type.encoding())
            if not out.state:
                self._sampled(member, port, out.type.encoding())
        member.runner = Runner(spec.node, node_cls, config, lambda port, msg: self._send(member, port, msg), ends,
                               set(spec.inputs))
        member.runner.node.audience = member.listened
        return member

    def _preview(self, member: Member, port: str, state: bool, encoding: str) -> None:
        """Publish a preview of output ``port``: of a data output, while someone subscribes to it; a model output's
        preview carries each model, cached for late joiners as the output itself is."""
        key = keys.copy_key(member.spec.prefix, keys.PREVIEW, member.name, port)
        if state:
            member.preview_publishers[port] = zext.declare_advanced_publisher(
                self.session, key, encoding=zenoh.Encoding(encoding), cache=zext.CacheConfig(max_samples=1),
                publisher_detection=True)
            return
        pub: Any = self.session.declare_publisher(  # Any: zenoh's stub says matching_status is a bool
            key, encoding=zenoh.Encoding(encoding))
        preview: Preview[Message] = Preview(lambda message: pub.put(encode(message), attachment=member.identity))

        def on_matching(status: zenoh.MatchingStatus) -> None:
            if status.matching:
                member.previews[port] = preview
            else:
                member.previews.pop(port, None)

        member.listeners.append(pub.declare_matching_listener(on_matching))
        member.preview_publishers[port] = pub
        if pub.matching_status.matching:
            member.previews[port] = preview

    def _sampled(self, member: Member, port: str, encoding: str) -> None:
        """Publish the sampled copy of data output ``port`` (``mocapflow.runtime.sampling``) while someone subscribes
        to it; as lossless as the output itself."""
        pub: Any = self.session.declare_publisher(  # Any: zenoh's stub says matching_status is a bool
            keys.copy_key(member.spec.prefix, keys.SAMPLED, member.name, port), encoding=zenoh.Encoding(encoding),
            congestion_control=zenoh.CongestionControl.BLOCK)

        def on_matching(status: zenoh.MatchingStatus) -> None:
            if status.matching:
                member.sampling.add(port)
            else:
                member.sampling.discard(port)

        member.listeners.append(pub.declare_matching_listener(on_matching))
        member.sampled_publishers[port] = pub
        if pub.matching_status.matching:
            member.sampling.add(port)

    # -- plumbing -------------------------------------------------------------------------------------------------
    def _subscribe(self, member: Member, port: str, key: str) -> Any:
        where = f"{member.name}/{port}"

        def on_sample(sample: zenoh.Sample) -> None:
            self.inbox.put(where, sample, end=sample.kind == zenoh.SampleKind.DELETE)

        if port in member.previewed:
            key = keys.copy_of(key, keys.PREVIEW)
        elif port in member.sampled:
            key = keys.copy_of(key, keys.SAMPLED)
        if member.runner.node.inputs[port].state:
            return subscribe_with_cache(self.session, key, on_sample)
        return self.session.declare_subscriber(key, on_sample)

    def _send(self, member: Member, port: str, message: Message) -> None:
        for target, target_port in member.routes.get(port, ()):
            self._local.append((target, target_port, message))
        payload = None
        if member.wanted[port]:  # always for a model
            payload = encode(message)
            member.publishers[port].put(payload, attachment=member.identity)
            if port in member.models:
                member.preview_publishers[port].put(payload, attachment=member.identity)
        if port in member.sampling and in_copy(message.frame, getattr(message, "rate", None)):
            member.sampled_publishers[port].put(payload or encode(message), attachment=member.identity)
        preview = member.previews.get(port)
        if preview is not None:
            preview.offer(message)

    def _end_outputs(self, member: Member) -> None:
        for port, out in member.runner.node.outputs.items():
            if not out.state:
                for target, target_port in member.routes.get(port, ()):
                    self._local.append((target, target_port, END))
                member.publishers[port].delete(attachment=member.identity)
                preview = member.previews.get(port)
                if preview is not None:
                    preview.end()
                member.preview_publishers[port].delete(attachment=member.identity)
                member.sampled_publishers[port].delete(attachment=member.identity)

    def _stats_loop(self) -> None:
        while not self.stop_event.wait(STATS_PERIOD_S):
            self.publish_stats()

    def publish_stats(self) -> None:
        for m in self.members.values():
            state = "failed" if m.runner.failed else \
                self.state if not m.runner.ended or self.state != "running" else "finished"
            figures = self.inbox.figures({f"{m.name}/{p}" for p in m.spec.inputs})
            stats = m.runner.stats.snapshot(m.name, state, **figures)
            if m is self.source:
                stats.clock_origin_ns = self.clock_origin_ns
            m.stats_pub.put(encode(stats))

    # -- running --------------------------------------------------------------------------------------------------
    def run(self) -> None:
        stats = threading.Thread(target=self._stats_loop, name="stats", daemon=True)
        stats.start()
        try:
            if self.source is not None:
                self._wait_for_peers()
            self.state = "running"
            self._loop()
        finally:
            self.state = "finished" if not self.stop_event.is_set() else "stopping"
            try:
                if self.source is not None and not self.source.runner.ended:  # stopped: its stream ends here
                    self.source.runner.ended = True
                    self._end_outputs(self.source)
                self._drain()
                self.finished_ok = all([m.runner.finish() for m in self.members.values()])
            finally:
                self.stop_event.set()
                stats.join()
                self.publish_stats()

    def _wait_for_peers(self) -> None:
        """Sources wait for every other node's liveliness token so that no first frame goes unheard."""
        wanted = set(self.spec.nodes()[0].peers) - set(self.members)
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

    def _loop(self) -> None:
        """Until every node has ended or a stop: what arrives from outside, then everything it causes inside the
        group, then the source's next frame when it is due (paced against the source's clock)."""
        src = self.source
        index, period, t0 = 0, 0.0, 0.0
        if src is not None:
            node = src.runner.node
            period = 1.0 / node.rate
            origin_ns = src.spec.clock_origin_ns or time.time_ns()
            resumed_s = (time.time_ns() - origin_ns) / 1e9 if src.spec.clock_origin_ns is not None else 0.0
            index = node.first_index(max(0.0, resumed_s))  # a first start begins at frame 0, however busy we are
            self.clock_origin_ns = node.clock_origin_ns = origin_ns
            self.publish_stats()
            # Frame i is due at origin + i * period, so a restarted source resumes on schedule and a late frame is
            # caught up at once instead of shifting every later frame.
            t0 = time.monotonic() - (time.time_ns() - origin_ns) / 1e9
        while not self.stop_event.is_set() and not all(m.runner.ended for m in self.members.values()):
            due = None
            if src is not None and not src.runner.ended:
                due = t0 + index * period if src.runner.node.paced else 0.0
            entry = self._next(0.1 if due is None else min(0.1, max(0.0, due - time.monotonic())))
            if entry is not None:
                self._heard = time.monotonic()
                self._external(entry)
                self._drain()
            elif time.monotonic() - max(self._heard, self._asked) >= QUIET_S:
                self._ask_ended()
            if self._finished:
                self._end_finished()
            if src is not None and due is not None and time.monotonic() >= due and not self.stop_event.is_set():
                if not src.runner.emit(index):
                    self._end_outputs(src)
                index += 1
                self._drain()
                if not src.runner.ended and src.runner.node.paced:
                    src.runner.prepare(index)  # a step of work ahead, in the time left before the frame is due, if any

    def _waiting(self) -> dict[tuple[str, str], str]:
        """The data inputs from outside that have not ended, as (member, port), each with the node whose output it
        is (its guard's upstream)."""
        return {(m.name, port): guard.upstream for m in self.members.values() for port, guard in m.guards.items()
                if port not in m.internal and port not in m.runner.ended_inputs}

    def _ask_ended(self) -> None:
        """Ask the launcher which nodes have finished (``keys.ended_key``), for inputs whose end of stream may have
        gone by before this process listened: it started late, or restarted after a crash. Asked after ``QUIET_S`` of
        silence, so that nothing the upstream sent before its end is still on its way; answered on Zenoh's thread,
        taken up by ``_end_finished``."""
        self._asked = time.monotonic()
        if not self._waiting():
            return

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                self._finished.append(str(reply.ok.key_expr).rsplit("/", 1)[-1])

        self.session.get(keys.ended_key(self.spec.prefix, "*"), on_reply, timeout=QUIET_S)

    def _end_finished(self) -> None:
        """End the inputs whose upstream node the launcher said has finished."""
        finished = set()
        while self._finished:
            finished.add(self._finished.popleft())
        for (name, port), upstream in self._waiting().items():
            if upstream in finished:
                log.info("%s: input %r had ended before this process listened (%s has finished)", name, port,
                         upstream)
                self._input_ended(self.members[name], port)
        self._drain()

    def _drain(self) -> None:
        """Hand over, in order, everything the group's members published for one another."""
        while self._local:
            member, port, message = self._local.popleft()
            if message is END:
                self._input_ended(member, port)
                continue
            if not member.runner.node.inputs[port].state:
                if not self._takes(member, port, message):
                    continue
                member.runner.count_in(port, message)
            member.runner.handle(port, [message])

    @staticmethod
    def _takes(member: Member, port: str, item: Any, skipped: int = 0) -> bool:
        """Whether the node takes the next message on data input ``port`` (``item``: the message, or its sample
        still undecoded); one it passes over on a ``latest`` input is held, the newest, for the input's end."""
        if not member.runner.wants(port, skipped):
            if port in member.latest:
                member.held[port] = item
            return False
        member.held.pop(port, None)
        return True

    def _input_ended(self, member: Member, port: str) -> None:
        """Input ``port`` has ended: the newest message the node passed over on it, if it is a ``latest`` input, is
        handed over after all (a sink that shows a sample of a stream, a viewer at its display rate, always shows
        its last frame); then the node's outputs end if that was the last input it waited for."""
        held = member.held.pop(port, None)
        if held is not None:
            member.runner.take_back(port)
            if isinstance(held, zenoh.Sample):
                held = self._decode(member, port, held, 0)
            else:
                member.runner.count_in(port, held)
            if held is not None:
                member.runner.handle(port, [held])
        if member.runner.end_of(port):
            self._end_outputs(member)

    def _next(self, timeout: float) -> Entry[zenoh.Sample] | None:
        """The next message from outside: one set aside while waiting for feedback first, else the inbox's."""
        return self._deferred.popleft() if self._deferred else self.inbox.get(timeout=timeout)

    def _external(self, entry: Entry[zenoh.Sample]) -> None:
        """Handle ``entry`` and whatever queued after it on the same input, in one batch."""
        name, _, port = entry.port.partition("/")
        member = self.members[name]
        sample = entry.item
        if entry.end:
            if port in member.guards and not member.guards[port].accept_end(_identity(sample)):
                member.runner.stats.refused += 1
                member.runner.report_error(f"input {port!r}", Refused(
                    f"end of stream from {_who(sample)}, not from the stream's publisher: ignored"))
            else:
                self._input_ended(member, port)
            return
        # A node that fell behind catches up on what has queued on this input since, in one batch.
        batch = [(sample, entry.skipped)]
        while len(batch) < MAX_BATCH:
            following = self._next(0)
            if following is None:
                break
            if following.port != entry.port or following.end:
                self._deferred.appendleft(following)
                break
            batch.append((following.item, following.skipped))
        messages = []
        for sample, skipped in batch:
            if self._takes(member, port, sample, skipped):
                message = self._decode(member, port, sample, skipped)
                if message is not None:
                    messages.append(message)
        if type(member.runner.node).process_batch is not Node.process_batch:
            member.runner.handle(port, messages)  # vectorised: the batch at once
            return
        for message in messages:  # one at a time, each followed by all it causes inside the group
            if port not in member.spec.wait_for and not member.runner.node.inputs[port].state:
                self._wait_for(member, message.frame)
            member.runner.handle(port, [message])
            self._drain()

    def _wait_for(self, member: Member, frame: int) -> None:
        """Before ``frame`` is handled, wait (each up to its bound) for the inputs the graph says to wait for (the
        filler's prediction for that frame) to reach it; what else arrives meanwhile is set aside, in order. A frame
        handled without them is counted (``unpaired``)."""
        for port, bound_ms in member.spec.wait_for.items():
            if port in member.internal:  # handed over inside the group: it is there already
                continue
            deadline = time.monotonic() + bound_ms / 1e3
            held: list[Entry[zenoh.Sample]] = []
            while member.runner.last_frame(port) < frame and port not in member.runner.ended_inputs:
                left = deadline - time.monotonic()
                entry = self.inbox.get(timeout=left) if left > 0 else None
                if entry is None:
                    member.runner.stats.unpaired += 1
                    break
                if entry.port == f"{member.name}/{port}":
                    self._external(entry)
                else:
                    held.append(entry)
            self._deferred.extend(held)

    def _decode(self, member: Member, port: str, sample: zenoh.Sample, skipped: int) -> Message | None:
        spec = member.runner.node.inputs[port]
        try:
            message = decode(sample.payload.to_bytes(), spec.type)
        except DecodeError as exc:
            member.runner.report_error(f"input {port!r} ({sample.key_expr})", exc)
            return None
        if not spec.state:
            if port in member.guards:
                guard = member.guards[port]
                try:
                    guard.check_source(_identity(sample))
                    message = guard.check_frame(message)
                except Refused as exc:
                    member.runner.stats.frames_in += 1
                    member.runner.stats.refused += 1
                    member.runner.report_error(f"input {port!r} ({_who(sample)})", exc)
                    return None
            if port in member.previewed:
                skipped = member.runner.thinned(port, message.frame, skipped)
            elif port in member.sampled:
                skipped = member.runner.thinned(port, message.frame, skipped,
                                                base_stride(getattr(message, "rate", None)))
            member.runner.count_in(port, message, skipped)
        return message


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
        classes = {n.node: load(n.plugin) for n in spec.nodes()}
        configs = {n.node: classes[n.node].Config.model_validate(n.config) for n in spec.nodes()}
        # a group runs at the priority of its most favoured member
        nice = min(n.nice for n in spec.nodes())
        if nice:
            os.nice(nice)
        if spec.cpus:  # before the session opens, so that its threads run there too
            os.sched_setaffinity(0, spec.cpus)
        if spec.cpu == "idle":
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
        elif spec.cpu == "realtime":  # before the session opens, so that its threads run so too
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(REALTIME_PRIORITY))
            except (OSError, AttributeError):  # no right to it, or a system without it (Linux's only)
                log.warning("node %s: 'cpu: realtime' needs Linux and the right to real-time priority (root, "
                            "CAP_SYS_NICE or an rtprio limit): running at normal priority", spec.node)
        session = open_client(spec.connect, spec.security)
    except (PluginNotFound, ValidationError, SecurityError) as exc:
        log.error("node %s: %s", spec.node, exc)
        return EXIT_CONFIG
    try:
        try:
            worker = Worker(spec, classes, configs, session)
        except Exception as exc:  # e.g. a file that cannot be opened: a configuration problem, not a crash
            log.error("node %s could not start: %s", spec.node, exc)
            return EXIT_CONFIG
        # What the interpreter, the libraries and the nodes' setup made lives as long as the process: out of the
        # collector's sight, whose full passes over it (about 200,000 objects) would stop the frame loop for 50-100 ms
        # each, several times a minute; the collector then only sees what the stream makes
        gc.freeze()
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
