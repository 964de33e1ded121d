"""``mocapflow run``: an embedded router, one supervised process per node, a live status table, a clean stop.

Stopping is ordered (see ``Supervisor.shutdown``): sources first, their end-of-stream drains the graph, every node
flushes (a recorder writes its file). Nodes die with the launcher (PR_SET_PDEATHSIG), so no process outlives a run.

Nodes placed on machines (``machine: NAME``) run under that machine's agent (``mocapflow.runtime.agent``): the
launcher joins the lab's router, waits for the agents, hands each its nodes, shows them in its table with their
machine, and stops them together with its own. An agent that disappears is reported; its nodes follow their restart
policy: ``on-failure`` nodes are deployed again when the agent comes back within the agent timeout, the others fail.
"""

from __future__ import annotations

import queue
import signal
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import nullcontext
from pathlib import Path
from typing import IO, Any

import orjson
import zenoh

from mocapflow.errors import GraphError, MocapflowError
from mocapflow.messages import MESSAGE_TYPES, NodeStats, json_schema
from mocapflow.runtime import keys
from mocapflow.runtime.graph import NAME, Graph, end_inputs
from mocapflow.runtime.kernels import compile_kernels
from mocapflow.runtime.node import Node
from mocapflow.runtime.protocol import (
    Placement,
    keep_clock_origin,
)
from mocapflow.runtime.remote import Agents, RemoteNode
from mocapflow.runtime.security import security_path
from mocapflow.runtime.session import DEFAULT_ENDPOINT, open_client, open_router
from mocapflow.runtime.signals import stop_on_signals
from mocapflow.runtime.supervisor import Proc, Supervisor, place_on_cores
from mocapflow.runtime.worker import EXIT_CONFIG, EXIT_FINISH, WorkerSpec


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


def refuse_prefix_in_use(session: zenoh.Session, prefix: str) -> None:
    """Refuse to start a graph whose keys another live graph uses: both trackers would feed both recordings."""
    users = set()
    for key in (keys.launcher_key(prefix), keys.alive_key(prefix)):
        users |= {str(r.ok.key_expr) for r in session.liveliness().get(key, timeout=2.0) if r.ok is not None}
    if users:
        raise MocapflowError(f"keys {prefix}/... are in use by a running graph ({', '.join(sorted(users))}): stop it,"
                             " or give this graph another 'name' or 'prefix'")


def _backlog(stats: NodeStats | None) -> str:
    """Messages waiting in a node's inbox and how long the oldest has waited: ``12/48ms``."""
    return "-" if stats is None else f"{stats.backlog}/{stats.backlog_ms:.0f}ms"


class Launcher:
    def __init__(self, graph: Graph, classes: dict[str, type[Node]], *, duration: float | None = None,
                 listen: list[str] | None = None, connect: list[str] | None = None, out: IO[str] = sys.stdout,
                 security: str | Path | None = None, agent_timeout: float = 30.0,
                 summary: str | Path | None = None, timeout: float | None = None) -> None:
        self.graph = graph
        self.summary = Path(summary) if summary else None
        self.timeout = timeout
        self.prefix = graph.key_prefix
        self.duration = duration
        self.out = out
        self.tty = out.isatty()
        self.connect = list(connect or graph.zenoh.connect)
        self.listen = list(listen or graph.zenoh.listen or ([] if self.connect else [DEFAULT_ENDPOINT]))
        self.security = security_path(security)
        self.agent_timeout = agent_timeout
        placed = {name: spec.machine for name, spec in graph.nodes.items() if spec.machine}
        for name, machine in placed.items():
            if not NAME.match(machine):
                raise GraphError(f"nodes.{name}.machine: {machine!r} must be letters, digits, '-' or '_'")
        if placed and not self.connect:
            raise GraphError(
                f"nodes {', '.join(placed)} are placed on machines, whose agents are reached through the lab's"
                " router: pass --connect ENDPOINT (see docs/lab-deployment.md), or remove 'machine' to run here"
            )
        endpoints = self.connect or client_endpoints(self.listen)
        self.run_id = uuid.uuid4().hex[:12]
        ends = end_inputs(graph, classes)
        specs = {
            name: WorkerSpec(
                node=name, plugin=spec.plugin, config=spec.config, prefix=self.prefix,
                inputs={p: f"{self.prefix}/{link}" for p, link in spec.inputs.items()},
                connect=endpoints, peers=list(graph.nodes), end_inputs=ends[name],
                security=str(self.security) if self.security else None, limits=graph.limits,
                run=self.run_id, queue=spec.queue, queue_size=spec.queue_size, wait_for=spec.wait_for, nice=spec.nice,
                cpu=spec.cpu, linked=graph.linked_outputs(name, classes),
            )
            for name, spec in graph.nodes.items()
        }
        all_procs = {
            name: Proc(spec=specs[name], source=classes[name].is_source(), restart=spec.restart,
                       max_restarts=spec.max_restarts)
            for name, spec in graph.nodes.items() if not spec.group
        }
        for group, members in graph.groups().items():
            # One process for the group, restarted as one: with the strictest restart policy of its members.
            nodes = [graph.nodes[m] for m in members]
            all_procs[group] = Proc(
                spec=specs[members[0]].model_copy(update={
                    "node": group, "plugin": "group", "members": [specs[m] for m in members], "inputs": {},
                    "queue": {}, "queue_size": max(n.queue_size for n in nodes),
                    "cpu": "own" if any(n.cpu == "own" for n in nodes) else
                    "realtime" if any(n.cpu == "realtime" for n in nodes) else
                    "idle" if all(n.cpu == "idle" for n in nodes) else "shared"}),
                source=any(classes[m].is_source() for m in members),
                restart="never" if any(n.restart == "never" for n in nodes) else "on-failure",
                max_restarts=min(n.max_restarts for n in nodes),
            )
            specs.update({m.node: m for m in all_procs[group].spec.members})  # the very specs the group runs
        local = [p for name, p in all_procs.items() if name not in placed]
        place_on_cores(local, out, confine_caller=True)
        self.supervisor = Supervisor(local)
        self.procs = self.supervisor.procs
        self.remote = {
            name: RemoteNode(Placement(spec=p.spec, source=p.source, restart=p.restart, max_restarts=p.max_restarts),
                             placed[name])
            for name, p in all_procs.items() if name in placed
        }
        self.specs = specs
        # the compiled kernels of the nodes run here (an agent makes every kernel ready when it starts)
        self.kernels = tuple(dict.fromkeys(load for name in graph.nodes if name not in placed
                                           for load in classes[name].kernels))
        self.lines = self.supervisor.lines
        self.stats: dict[str, NodeStats] = {}
        self.stop_reason: str | None = None
        self._table_height = 0

    # -- display --------------------------------------------------------------------------------------------------
    def _on_stats(self, sample: zenoh.Sample) -> None:
        stats = keep_clock_origin(self.specs, sample)
        if stats is not None and stats.node in self.specs:
            self.stats[stats.node] = stats

    def _serve_ended(self, session: zenoh.Session) -> zenoh.Queryable:
        """Answer ``{prefix}/_ended/{node}`` for each node that has finished (its last statistics say so): its output
        streams have ended. A node that (re)starts after an end of stream went by asks here (``worker``)."""

        def on_query(query: zenoh.Query) -> None:
            for name, stats in list(self.stats.items()):
                key = keys.ended_key(self.prefix, name)
                if stats.state == "finished" and query.key_expr.intersects(zenoh.KeyExpr(key)):
                    query.reply(key, b"")

        return session.declare_queryable(keys.ended_key(self.prefix, "*"), on_query)

    def _rows(self) -> Iterator[tuple[str, str, str, str, int | None, int]]:
        """(node, plugin, machine, state, pid, restarts) in graph order."""
        for name in self.graph.nodes:
            if name in self.remote:
                r = self.remote[name]
                yield name, r.spec.plugin, r.machine, self._state(name, r.state, r.exit_code), r.pid, r.restarts
            else:
                p = self.procs[self.graph.process_of(name)]
                yield (name, self.graph.nodes[name].plugin, "local", self._state(name, p.state, p.exit_code), p.pid,
                       p.restarts)

    def _state(self, name: str, state: str, exit_code: int | None) -> str:
        """A node's state: its process's, but finished for a member of a group whose process failed because another
        member's finish() did, as the members' last statistics tell."""
        if state != "failed" or exit_code != EXIT_FINISH:
            return state
        group = self.graph.groups().get(self.graph.process_of(name), [name])
        failed = {m for m in group if m in self.stats and self.stats[m].state == "failed"}
        return "finished" if failed and name not in failed else "failed"

    def summarise(self) -> dict[str, dict[str, Any]]:
        """Per node: plugin, machine, state, restarts and its last statistics, as written by ``--summary``."""
        return {
            name: {"plugin": plugin, "machine": machine, "state": state, "restarts": restarts,
                   **(self.stats[name].model_dump(exclude={"node", "state"}) if name in self.stats else {})}
            for name, plugin, machine, state, _pid, restarts in self._rows()
        }

    def table(self) -> str:
        where = f"{'MACHINE':<14}" if self.remote else ""
        head = f"{'NODE':<14}{'PLUGIN':<20}{where}{'STATE':<11}{'PID':>8}{'RATE Hz':>9}{'P50 ms':>8}{'P99 ms':>8}" \
               f"{'IN':>8}{'OUT':>8}{'DROPS':>6}{'SKIP':>7}{'BACKLOG':>12}{'ERR':>5}{'RESTARTS':>9}"
        rows = [head]
        for name, plugin, machine, state, pid, restarts in self._rows():
            s = self.stats.get(name)
            fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
            where = f"{machine:<14.14}" if self.remote else ""
            rows.append(
                f"{name:<14.14}{plugin:<20.20}{where}{state:<11}{pid or '-':>8}"
                f"{fmt(s.rate_hz if s else None):>9}{fmt(s.latency_p50_ms if s else None):>8}"
                f"{fmt(s.latency_p99_ms if s else None):>8}{(s.frames_in if s else 0):>8}"
                f"{(s.frames_out if s else 0):>8}"
                f"{(s.drops if s else 0):>6}{(s.skipped if s else 0):>7}{_backlog(s):>12}{(s.errors if s else 0):>5}"
                f"{restarts:>9}"
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

    # -- state of the whole run -----------------------------------------------------------------------------------
    def _all_finished(self) -> bool:
        return self.supervisor.all_finished() and all(r.state == "finished" for r in self.remote.values())

    def _failed(self, final: bool = False) -> list[str]:
        """Nodes that failed for good, locally or on an agent; at the end of a run, also those whose agent was lost
        and is not back."""
        return [name for name, _, _, state, _, _ in self._rows() if state == "failed" or (final and state == "lost")]

    def _exit_code(self, name: str) -> int | None:
        return self.remote[name].exit_code if name in self.remote else self.procs[self.graph.process_of(name)].exit_code

    def _tail(self, name: str) -> list[str]:
        proc = self.remote[name] if name in self.remote else self.procs[self.graph.process_of(name)]
        return proc.log_tail[-5:]

    # -- main loop ------------------------------------------------------------------------------------------------
    def run(self) -> int:
        compile_kernels(self.out, *self.kernels)
        session = (open_router(self.listen, self.security) if not self.connect
                   else open_client(self.connect, self.security, self.timeout))
        stop = threading.Event()

        def stop_reason(signum: signal.Signals) -> None:
            self.stop_reason = self.stop_reason or signum.name

        agents = Agents(session, self.prefix, self.remote, self.lines, self.agent_timeout) if self.remote else None
        try:
            refuse_prefix_in_use(session, self.prefix)
            with stop_on_signals(stop, on_signal=stop_reason), \
                    session.liveliness().declare_token(keys.launcher_key(self.prefix, self.run_id)), \
                    session.declare_subscriber(keys.stats_key(self.prefix), self._on_stats), \
                    serve_schemas(session, self.prefix), self._serve_ended(session), agents or nullcontext():
                where = ", ".join(self.connect) if self.connect else f"embedded router on {', '.join(self.listen)}"
                self.out.write(f"mocapflow: running {self.graph.name!r} ({len(self.specs)} nodes, {where}, "
                               f"keys {self.prefix}/...)\n")
                try:
                    if agents is not None:
                        self.out.write(f"mocapflow: waiting for agents {', '.join(agents.machines)}\n")
                        self.out.flush()
                        agents.wait(stop)
                    if not stop.is_set():
                        if agents is not None:
                            agents.deploy_all()
                        self.supervisor.start()
                        self._loop(stop, agents)
                finally:
                    finish_remote = agents.stop(self._flush_lines) if agents is not None else None
                    self.supervisor.shutdown(self._flush_lines)
                    if finish_remote is not None:
                        finish_remote()
                self._flush_lines()
                self._clear_table()
                self.out.write(self.table() + "\n")
        finally:
            session.close()
        if self.summary is not None:
            self.summary.parent.mkdir(parents=True, exist_ok=True)
            self.summary.write_bytes(orjson.dumps(self.summarise(), option=orjson.OPT_INDENT_2))
        failed = self._failed(final=True)
        if failed:
            self.out.write(f"mocapflow: failed: {', '.join(failed)}\n")
            for name in failed:
                tail = self._tail(name)
                if tail:
                    self.out.write("\n".join(f"  [{name}] {line}" for line in tail) + "\n")
            return EXIT_CONFIG if any(self._exit_code(name) == EXIT_CONFIG for name in failed) else 1
        self.out.write(f"mocapflow: stopped ({self.stop_reason or 'all nodes finished'})\n")
        return 0

    def _loop(self, stop: threading.Event, agents: Agents | None) -> None:
        start = time.monotonic()
        last_draw = 0.0
        period = 0.5 if self.tty else 5.0
        while not stop.wait(0.05):
            self.supervisor.poll()
            if agents is not None:
                agents.poll()
            self._flush_lines()
            elapsed = time.monotonic() - start
            if self.duration is not None and elapsed >= self.duration:
                self.stop_reason = "duration reached"
                break
            if self._all_finished():
                break
            if self._failed():
                self.stop_reason = "a node failed"
                break
            if elapsed - last_draw >= period:
                last_draw = elapsed
                self._draw(elapsed)

