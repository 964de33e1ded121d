"""``mocapflow run``: an embedded router, one supervised process per node, a live status table, a clean stop.

Stopping is ordered (see ``Supervisor.shutdown``): sources first, their end-of-stream drains the graph, every node
flushes (a recorder writes its file). Nodes die with the launcher (PR_SET_PDEATHSIG), so no process outlives a run.
"""

from __future__ import annotations

import queue
import signal
import sys
import threading
import time
from typing import IO

import orjson
import zenoh

from mocapflow.errors import GraphError
from mocapflow.messages import MESSAGE_TYPES, DecodeError, NodeStats, decode, json_schema
from mocapflow.runtime import keys
from mocapflow.runtime.graph import Graph
from mocapflow.runtime.node import Node
from mocapflow.runtime.session import DEFAULT_ENDPOINT, open_client, open_router
from mocapflow.runtime.supervisor import Proc, Supervisor
from mocapflow.runtime.worker import WorkerSpec

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
        self.supervisor = Supervisor([
            Proc(
                spec=WorkerSpec(
                    node=name, plugin=spec.plugin, config=spec.config, prefix=self.prefix,
                    inputs={p: f"{self.prefix}/{link}" for p, link in spec.inputs.items()},
                    connect=endpoints, peers=list(graph.nodes),
                ),
                source=classes[name].is_source(), restart=spec.restart, max_restarts=spec.max_restarts,
            )
            for name, spec in graph.nodes.items()
        ])
        self.procs = self.supervisor.procs
        self.lines = self.supervisor.lines
        self.stats: dict[str, NodeStats] = {}
        self.stop_reason: str | None = None
        self._table_height = 0

    # -- display --------------------------------------------------------------------------------------------------
    def _on_stats(self, sample: zenoh.Sample) -> None:
        try:
            stats = decode(sample.payload.to_bytes(), NodeStats)
        except DecodeError:
            return
        proc = self.procs.get(stats.node)
        if proc is not None:
            self.stats[stats.node] = stats
            if stats.clock_origin_ns is not None:
                proc.spec.clock_origin_ns = stats.clock_origin_ns

    def table(self) -> str:
        head = f"{'NODE':<14}{'PLUGIN':<20}{'STATE':<11}{'PID':>8}{'RATE Hz':>9}{'P50 ms':>8}{'P99 ms':>8}" \
               f"{'IN':>8}{'OUT':>8}{'DROPS':>6}{'ERR':>5}{'RESTARTS':>9}"
        rows = [head]
        for p in self.procs.values():
            s = self.stats.get(p.name)
            fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
            pid = p.pid or "-"
            rows.append(
                f"{p.name:<14.14}{p.spec.plugin:<20.20}{p.state:<11}{pid:>8}"
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
                self.supervisor.start()
                start = time.monotonic()
                last_draw = 0.0
                period = 0.5 if self.tty else 5.0
                while not stop.wait(0.05):
                    self.supervisor.poll()
                    self._flush_lines()
                    elapsed = time.monotonic() - start
                    if self.duration is not None and elapsed >= self.duration:
                        self.stop_reason = "duration reached"
                        break
                    if self.supervisor.all_finished():
                        break
                    if self.supervisor.failed():
                        self.stop_reason = "a node failed"
                        break
                    if elapsed - last_draw >= period:
                        last_draw = elapsed
                        self._draw(elapsed)
                self.supervisor.shutdown(self._flush_lines)
                self._flush_lines()
                self._clear_table()
                self.out.write(self.table() + "\n")
        finally:
            for s, handler in old.items():
                signal.signal(s, handler)
            session.close()
        failed = [p.name for p in self.supervisor.failed()]
        if failed:
            self.out.write(f"mocapflow: failed: {', '.join(failed)}\n")
            for name in failed:
                tail = self.procs[name].log_tail[-5:]
                if tail:
                    self.out.write("\n".join(f"  [{name}] {line}" for line in tail) + "\n")
            return 1
        self.out.write(f"mocapflow: stopped ({self.stop_reason or 'all nodes finished'})\n")
        return 0
