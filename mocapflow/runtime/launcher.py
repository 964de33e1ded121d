"""``mocapflow run``: an embedded router, one process per node, supervision, a live status table, a clean stop.

Stopping is ordered: sources are asked to stop first, their end-of-stream travels down the graph, every node
flushes (a recorder writes its file), and only nodes that have not finished within a grace period are terminated,
then killed. Nodes die with the launcher (PR_SET_PDEATHSIG), so no process outlives a run.
"""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import IO

import zenoh

from mocapflow.errors import GraphError
from mocapflow.messages import MESSAGE_TYPES, NodeStats, DecodeError, decode, json_schema
from mocapflow.runtime import keys
from mocapflow.runtime.graph import Graph, NodeSpec
from mocapflow.runtime.node import Node
from mocapflow.runtime.session import DEFAULT_ENDPOINT, open_client, open_router
from mocapflow.runtime.worker import EXIT_CONFIG, WorkerSpec

import orjson

DRAIN_S = 10.0
TERM_S = 3.0
HEALTHY_S = 30.0


@dataclass
class Proc:
    name: str
    spec: WorkerSpec
    node: NodeSpec
    source: bool
    popen: subprocess.Popen[bytes] | None = None
    state: str = "starting"
    restarts: int = 0
    failures: int = 0
    next_start: float = 0.0
    started_at: float = 0.0
    exit_code: int | None = None
    stats: NodeStats | None = None
    log_tail: list[str] = field(default_factory=list)


def client_endpoints(listen: list[str]) -> list[str]:
    """Endpoints a local client uses to reach a router listening on ``listen`` (0.0.0.0 -> loopback)."""
    return [ep.replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]") for ep in listen]


def serve_schemas(session: zenoh.Session, prefix: str) -> zenoh.Queryable:
    """Answer ``{prefix}/_schema/<Type>`` with that message type's JSON Schema (``*`` answers every type)."""

    def on_query(query: zenoh.Query) -> None:
        wanted = str(query.key_expr).rsplit("/", 1)[-1]
        for name, cls in MESSAGE_TYPES.items():
            if wanted in ("*", "**", name):
                query.reply(keys.schema_key(prefix, name), orjson.dumps(json_schema(cls)),
                            encoding=zenoh.Encoding.APPLICATION_JSON)

    return session.declare_queryable(keys.schema_key(prefix, "**"), on_query)


class Launcher:
    def __init__(self, graph: Graph, classes: dict[str, type[Node]], *, duration: float | None = None,
                 listen: list[str] | None = None, connect: list[str] | None = None, out: IO[str] = sys.stdout) -> None:
        self.graph = graph
        self.prefix = graph.key_prefix
        self.duration = duration
        self.out = out
        self.tty = out.isatty()
        self.connect = list(connect or graph.zenoh.connect)
        self.listen = list(listen or graph.zenoh.listen or ([] if self.connect else [DEFAULT_ENDPOINT]))
        placed = [n for n, s in graph.nodes.items() if s.machine]
        if placed:
            raise GraphError(
                f"nodes {', '.join(placed)} are placed on machines, which needs agents; this launcher runs every node"
                " locally: remove 'machine' to run here"
            )
        endpoints = self.connect or client_endpoints(self.listen)
        self.procs = {
            name: Proc(
                name=name,
                node=spec,
                source=classes[name].is_source(),
                spec=WorkerSpec(
                    node=name, plugin=spec.plugin, config=spec.config, prefix=self.prefix,
                    inputs={p: f"{self.prefix}/{link}" for p, link in spec.inputs.items()},
                    connect=endpoints, peers=list(graph.nodes),
                ),
            )
            for name, spec in graph.nodes.items()
        }
        self.lines: queue.Queue[str] = queue.Queue()
        self.stop_reason: str | None = None
        self._table_height = 0

    # -- processes ------------------------------------------------------------------------------------------------
    def _spawn(self, proc: Proc) -> None:
        proc.popen = subprocess.Popen(
            [sys.executable, "-m", "mocapflow.runtime.worker", proc.spec.model_dump_json()],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
        )
        proc.state, proc.started_at, proc.exit_code = "running", time.monotonic(), None
        threading.Thread(target=self._pump, args=(proc, proc.popen.stdout), daemon=True).start()

    def _pump(self, proc: Proc, stream: IO[bytes]) -> None:
        for raw in stream:
            line = raw.decode(errors="replace").rstrip()
            proc.log_tail = (proc.log_tail + [line])[-20:]
            self.lines.put(f"[{proc.name}] {line}")

    def _poll(self) -> None:
        now = time.monotonic()
        for proc in self.procs.values():
            if proc.state == "restarting" and now >= proc.next_start and not self.stop_reason:
                self._spawn(proc)
                continue
            if proc.popen is None or proc.state != "running" or proc.popen.poll() is None:
                continue
            code = proc.exit_code = proc.popen.returncode
            if code == 0:
                proc.state = "finished"
                continue
            if now - proc.started_at > HEALTHY_S:
                proc.failures = 0
            proc.failures += 1
            why = "configuration error" if code == EXIT_CONFIG else f"exit code {code}"
            if self.stop_reason or code == EXIT_CONFIG or proc.node.restart == "never" or proc.failures > proc.node.max_restarts:
                proc.state = "failed"
                self.lines.put(f"[{proc.name}] failed for good ({why})")
            else:
                delay = min(0.5 * 2 ** (proc.failures - 1), 10.0)
                proc.state, proc.next_start = "restarting", now + delay
                proc.restarts += 1
                self.lines.put(f"[{proc.name}] stopped ({why}); restart {proc.restarts} in {delay:.1f} s")

    def _alive(self) -> list[Proc]:
        return [p for p in self.procs.values() if p.popen is not None and p.popen.poll() is None]

    def _signal(self, procs: list[Proc], sig: int) -> None:
        for proc in procs:
            if proc.popen is not None and proc.popen.poll() is None:
                proc.popen.send_signal(sig)

    def _shutdown(self) -> None:
        """Sources first, then let end-of-stream drain the graph, then terminate, then kill."""
        self._signal([p for p in self.procs.values() if p.source], signal.SIGTERM)
        for grace, sig in ((DRAIN_S, signal.SIGTERM), (TERM_S, signal.SIGKILL), (TERM_S, None)):
            deadline = time.monotonic() + grace
            while self._alive() and time.monotonic() < deadline:
                self._poll()
                self._flush_lines()
                time.sleep(0.05)
            if sig is not None:
                self._signal(self._alive(), sig)
        for proc in self.procs.values():
            if proc.popen is not None:
                proc.popen.wait()
        self._poll()

    # -- display --------------------------------------------------------------------------------------------------
    def _on_stats(self, sample: zenoh.Sample) -> None:
        try:
            stats = decode(sample.payload.to_bytes(), NodeStats)
        except DecodeError:
            return
        proc = self.procs.get(stats.node)
        if proc is not None:
            proc.stats = stats
            if stats.clock_origin_ns is not None:
                proc.spec.clock_origin_ns = stats.clock_origin_ns

    def table(self) -> str:
        head = f"{'NODE':<14}{'PLUGIN':<20}{'STATE':<11}{'PID':>8}{'RATE Hz':>9}{'P50 ms':>8}{'P99 ms':>8}" \
               f"{'IN':>8}{'OUT':>8}{'DROPS':>6}{'ERR':>5}{'RESTARTS':>9}"
        rows = [head]
        for p in self.procs.values():
            s = p.stats
            fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
            pid = p.popen.pid if p.popen else "-"
            rows.append(
                f"{p.name:<14.14}{p.node.plugin:<20.20}{p.state:<11}{pid:>8}"
                f"{fmt(s.rate_hz if s else None):>9}{fmt(s.latency_p50_ms if s else None):>8}"
                f"{fmt(s.latency_p99_ms if s else None):>8}{(s.frames_in if s else 0):>8}{(s.frames_out if s else 0):>8}"
                f"{(s.drops if s else 0):>6}{(s.errors if s else 0):>5}{p.restarts:>9}"
            )
        return "\n".join(rows)

    def _flush_lines(self) -> None:
        pending = []
        while True:
            try:
                pending.append(self.lines.get_nowait())
            except queue.Empty:
                break
        if pending:
            self._clear_table()
            self.out.write("\n".join(pending) + "\n")
            self.out.flush()

    def _clear_table(self) -> None:
        if self.tty and self._table_height:
            self.out.write(f"\x1b[{self._table_height}F\x1b[J")
            self._table_height = 0

    def _draw(self, elapsed: float) -> None:
        text = f"{self.graph.name}  {elapsed:6.1f} s  (Ctrl-C to stop)\n{self.table()}\n"
        self._clear_table()
        self.out.write(text)
        self.out.flush()
        self._table_height = text.count("\n")

    # -- main loop ------------------------------------------------------------------------------------------------
    def run(self) -> int:
        session = open_router(self.listen) if not self.connect else open_client(self.connect)
        stop = threading.Event()

        def request_stop(signum: int, _frame: object) -> None:
            self.stop_reason = self.stop_reason or signal.Signals(signum).name
            stop.set()

        old = {s: signal.signal(s, request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            with session.declare_subscriber(keys.stats_key(self.prefix), self._on_stats), \
                    serve_schemas(session, self.prefix):
                where = ", ".join(self.connect) if self.connect else f"embedded router on {', '.join(self.listen)}"
                self.out.write(f"mocapflow: running {self.graph.name!r} ({len(self.procs)} nodes, {where}, keys {self.prefix}/...)\n")
                for proc in self.procs.values():
                    self._spawn(proc)
                start = time.monotonic()
                last_draw = 0.0
                period = 0.5 if self.tty else 5.0
                while not stop.wait(0.05):
                    self._poll()
                    self._flush_lines()
                    elapsed = time.monotonic() - start
                    if self.duration is not None and elapsed >= self.duration:
                        self.stop_reason = "duration reached"
                        break
                    if all(p.state == "finished" for p in self.procs.values()):
                        break
                    if any(p.state == "failed" for p in self.procs.values()):
                        self.stop_reason = "a node failed"
                        break
                    if elapsed - last_draw >= period:
                        last_draw = elapsed
                        self._draw(elapsed)
                self._shutdown()
                self._flush_lines()
                self._clear_table()
                self.out.write(self.table() + "\n")
        finally:
            for s, handler in old.items():
                signal.signal(s, handler)
            session.close()
        failed = [p.name for p in self.procs.values() if p.state == "failed"]
        if failed:
            self.out.write(f"mocapflow: failed: {', '.join(failed)}\n")
            for name in failed:
                tail = self.procs[name].log_tail[-5:]
                if tail:
                    self.out.write("\n".join(f"  [{name}] {line}" for line in tail) + "\n")
            return 1
        self.out.write(f"mocapflow: stopped ({self.stop_reason or 'all nodes finished'})\n")
        return 0
