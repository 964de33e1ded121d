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
from collections.abc import Callable, Iterator
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Self

import orjson
import zenoh
from pydantic import TypeAdapter, ValidationError

from mocapflow.errors import GraphError
from mocapflow.messages import MESSAGE_TYPES, NodeStats, json_schema
from mocapflow.runtime import keys
from mocapflow.runtime.agent import (
    AgentError,
    Deployment,
    Placement,
    ProcStatus,
    keep_clock_origin,
)
from mocapflow.runtime.graph import NAME, Graph, end_inputs
from mocapflow.runtime.keys import (
    agent_key,
    deploy_key,
    launcher_key,
    log_key,
    procs_key,
    stop_key,
)
from mocapflow.runtime.node import Node
from mocapflow.runtime.security import security_path
from mocapflow.runtime.session import DEFAULT_ENDPOINT, open_client, open_router
from mocapflow.runtime.supervisor import DRAIN_S, TERM_S, Proc, Supervisor
from mocapflow.runtime.worker import WorkerSpec

AGENT_GRACE_S = 5.0  # an agent's token may vanish this long (it rejoins a restarted router) before it counts as lost
DEPLOY_TIMEOUT_S = 10.0
STOP_TIMEOUT_S = DRAIN_S + 2 * TERM_S + 5.0
STATUS_LIST = TypeAdapter(list[ProcStatus])


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


@dataclass
class RemoteNode:
    """A node an agent runs for this launcher, as that agent last reported it."""

    placement: Placement
    machine: str
    state: str = "deploying"
    pid: int | None = None
    agent_restarts: int = 0
    earlier_restarts: int = 0  # counted before its agent was lost, the new deployment included
    exit_code: int | None = None
    log_tail: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return self.placement.spec.node

    @property
    def spec(self) -> WorkerSpec:
        return self.placement.spec

    @property
    def restarts(self) -> int:
        return self.agent_restarts + self.earlier_restarts

    def update(self, status: ProcStatus) -> None:
        self.state, self.pid, self.exit_code = status.state, status.pid, status.exit_code
        self.agent_restarts = status.restarts


class Agents:
    """The launcher's side of the agent protocol: wait for agents, deploy, follow their reports, notice an agent
    lost, deploy again when it is back, and stop."""

    def __init__(self, session: zenoh.Session, prefix: str, nodes: dict[str, RemoteNode], lines: queue.Queue[str],
                 timeout: float) -> None:
        self.session = session
        self.prefix = prefix
        self.run = uuid.uuid4().hex[:12]
        self.nodes = nodes
        self.lines = lines
        self.timeout = timeout
        self.machines = sorted({n.machine for n in nodes.values()})
        self.present: set[str] = set()
        self.absent_since: dict[str, float] = {}
        self.lost: dict[str, float] = {}
        self.deployed: set[str] = set()
        self._declared: list[Any] = []

    # -- reports from agents (Zenoh callback threads) -----------------------------------------------------------
    def _on_agent(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        if sample.kind == zenoh.SampleKind.PUT:
            self.present.add(name)
        else:
            self.present.discard(name)

    def _on_status(self, sample: zenoh.Sample) -> None:
        try:
            status = ProcStatus.model_validate_json(sample.payload.to_bytes())
        except ValidationError:
            return
        node = self.nodes.get(status.node)
        if status.run == self.run and node is not None and node.machine not in self.lost:
            node.update(status)

    def _on_log(self, sample: zenoh.Sample) -> None:
        machine = str(sample.key_expr).rsplit("/", 1)[-1]
        line = sample.payload.to_string()
        name, sep, text = line[1:].partition("] ")
        node = self.nodes.get(name) if line.startswith("[") and sep else None
        if node is None:
            self.lines.put(f"[@{machine}] {line}")
            return
        node.log_tail = (node.log_tail + [text])[-20:]
        self.lines.put(f"[{name}@{machine}] {text}")

    # -- lifecycle ------------------------------------------------------------------------------------------------
    def __enter__(self) -> Self:
        liveliness = self.session.liveliness()
        self._declared = [
            liveliness.declare_subscriber(agent_key("*"), self._on_agent, history=True),
            self.session.declare_subscriber(procs_key(self.prefix), self._on_status),
            self.session.declare_subscriber(log_key(self.prefix), self._on_log),
            liveliness.declare_token(launcher_key(self.prefix, self.run)),
        ]
        return self

    def __exit__(self, *_exc: object) -> None:
        for declared in self._declared:
            declared.undeclare()

    def wait(self, stop: threading.Event) -> None:
        """Wait for every agent the graph names; after the timeout, name the missing ones."""
        deadline = time.monotonic() + self.timeout
        while not stop.is_set():
            missing = [m for m in self.machines if m not in self.present]
            if not missing:
                return
            if time.monotonic() > deadline:
                nodes = ", ".join(f"{n.name} on {n.machine}" for n in self.nodes.values() if n.machine in missing)
                raise AgentError(
                    f"no agent for machine(s) {', '.join(missing)} after {self.timeout:g} s ({nodes}); start"
                    f" `mocapflow agent --name MACHINE --connect ENDPOINT` there, joined to the same router"
                )
            stop.wait(0.05)

    def deploy(self, machine: str, nodes: list[RemoteNode]) -> None:
        """Hand ``nodes`` to ``machine``'s agent; an agent already running them just reports their state."""
        deployment = Deployment(run=self.run, prefix=self.prefix, nodes=[n.placement for n in nodes])
        replies = self.session.get(deploy_key(machine), payload=deployment.model_dump_json(),
                                   encoding=zenoh.Encoding.APPLICATION_JSON, timeout=DEPLOY_TIMEOUT_S)
        for reply in replies:
            if reply.err is not None:
                raise AgentError(reply.err.payload.to_string())
            self.deployed.add(machine)
            for status in STATUS_LIST.validate_json(reply.ok.payload.to_bytes()):
                if status.node in self.nodes:
                    self.nodes[status.node].update(status)
            return
        raise AgentError(f"agent {machine} did not answer the deployment within {DEPLOY_TIMEOUT_S:g} s")

    def deploy_all(self) -> None:
        for machine in self.machines:
            self.deploy(machine, [n for n in self.nodes.values() if n.machine == machine])

    def poll(self) -> None:
        """Notice agents that vanished while this launcher reaches the router, and deploy again on those back."""
        now = time.monotonic()
        connected = bool(self.session.info.routers_zid())
        for machine in self.machines:
            on_it = [n for n in self.nodes.values() if n.machine == machine]
            if machine in self.present:
                lost_at = self.lost.pop(machine, None)
                if self.absent_since.pop(machine, None) is not None or lost_at is not None:
                    self._back(machine, on_it, lost_at is not None)
                continue
            if not connected:  # the router is gone, not the agent: wait for both to rejoin
                self.absent_since.pop(machine, None)
                continue
            since = self.absent_since.setdefault(machine, now)
            if machine not in self.lost and now - since > AGENT_GRACE_S:
                self._lose(machine, on_it, now)
            elif machine in self.lost and now - self.lost[machine] > self.timeout:
                for node in on_it:
                    if node.state == "lost":
                        node.state = "failed"
                        self.lines.put(f"[{node.name}@{machine}] failed for good (agent {machine} did not come back"
                                       f" within {self.timeout:g} s)")

    def _lose(self, machine: str, nodes: list[RemoteNode], now: float) -> None:
        self.lost[machine] = now
        waiting = [n for n in nodes if n.state not in ("finished", "failed") and n.placement.restart != "never"]
        for node in nodes:
            if node.state not in ("finished", "failed"):
                node.state, node.pid = ("lost" if node in waiting else "failed"), None
        policy = f"; waiting up to {self.timeout:g} s for it to come back for {', '.join(n.name for n in waiting)}" \
            if waiting else ""
        self.lines.put(f"mocapflow: agent {machine} lost (nodes {', '.join(n.name for n in nodes)}){policy}")

    def _back(self, machine: str, nodes: list[RemoteNode], was_lost: bool) -> None:
        """An agent's token came back: a new agent, or the same one after a network outage. Deploying again is
        safe either way (an agent already running the nodes only reports them)."""
        again = [n for n in nodes if n.state not in ("finished", "failed")]
        if not again:
            return
        if was_lost:
            for node in again:
                node.earlier_restarts += node.agent_restarts + 1
                node.agent_restarts = 0
            self.lines.put(f"mocapflow: agent {machine} is back: deploying {', '.join(n.name for n in again)} again")
        try:
            self.deploy(machine, again)
        except AgentError as exc:
            self.lines.put(f"mocapflow: {exc}")
            for node in again:
                node.state = "failed"

    def stop(self, tick: Callable[[], None]) -> Callable[[], None]:
        """Ask every agent to stop this run now; return a function that waits for their answers (calling ``tick``
        meanwhile), so that local nodes can be stopped in between."""
        asked = [m for m in self.machines if m in self.deployed and m not in self.lost]
        pending = {m: self.session.get(stop_key(m), payload=self.run, timeout=STOP_TIMEOUT_S) for m in asked}

        def finish() -> None:
            answered: set[str] = set()
            while pending:
                for machine, replies in list(pending.items()):
                    try:
                        reply = replies.try_recv()
                    except zenoh.ZError:  # no more replies: answered, or timed out
                        del pending[machine]
                        continue
                    if reply is not None and reply.ok is not None:
                        answered.add(machine)
                        for status in STATUS_LIST.validate_json(reply.ok.payload.to_bytes()):
                            if status.node in self.nodes:
                                self.nodes[status.node].update(status)
                tick()
                time.sleep(0.05)
            for machine in asked:
                if machine not in answered:
                    self.lines.put(f"mocapflow: agent {machine} did not confirm the stop of its nodes")

        return finish


class Launcher:
    def __init__(self, graph: Graph, classes: dict[str, type[Node]], *, duration: float | None = None,
                 listen: list[str] | None = None, connect: list[str] | None = None, out: IO[str] = sys.stdout,
                 security: str | Path | None = None, agent_timeout: float = 30.0,
                 summary: str | Path | None = None) -> None:
        self.graph = graph
        self.summary = Path(summary) if summary else None
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
        ends = end_inputs(graph, classes)
        all_procs = {
            name: Proc(
                spec=WorkerSpec(
                    node=name, plugin=spec.plugin, config=spec.config, prefix=self.prefix,
                    inputs={p: f"{self.prefix}/{link}" for p, link in spec.inputs.items()},
                    connect=endpoints, peers=list(graph.nodes), end_inputs=ends[name],
                    security=str(self.security) if self.security else None,
                ),
                source=classes[name].is_source(), restart=spec.restart, max_restarts=spec.max_restarts,
            )
            for name, spec in graph.nodes.items()
        }
        self.supervisor = Supervisor([p for name, p in all_procs.items() if name not in placed])
        self.procs = self.supervisor.procs
        self.remote = {
            name: RemoteNode(Placement(spec=p.spec, source=p.source, restart=p.restart, max_restarts=p.max_restarts),
                             placed[name])
            for name, p in all_procs.items() if name in placed
        }
        self.specs = {name: p.spec for name, p in all_procs.items()}
        self.lines = self.supervisor.lines
        self.stats: dict[str, NodeStats] = {}
        self.stop_reason: str | None = None
        self._table_height = 0

    # -- display --------------------------------------------------------------------------------------------------
    def _on_stats(self, sample: zenoh.Sample) -> None:
        stats = keep_clock_origin(self.specs, sample)
        if stats is not None and stats.node in self.specs:
            self.stats[stats.node] = stats

    def _rows(self) -> Iterator[tuple[str, str, str, str, int | None, int]]:
        """(node, plugin, machine, state, pid, restarts) in graph order."""
        for name in self.graph.nodes:
            if name in self.remote:
                r = self.remote[name]
                yield name, r.spec.plugin, r.machine, r.state, r.pid, r.restarts
            else:
                p = self.procs[name]
                yield name, p.spec.plugin, "local", p.state, p.pid, p.restarts

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
               f"{'IN':>8}{'OUT':>8}{'DROPS':>6}{'ERR':>5}{'RESTARTS':>9}"
        rows = [head]
        for name, plugin, machine, state, pid, restarts in self._rows():
            s = self.stats.get(name)
            fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
            where = f"{machine:<14.14}" if self.remote else ""
            rows.append(
                f"{name:<14.14}{plugin:<20.20}{where}{state:<11}{pid or '-':>8}"
                f"{fmt(s.rate_hz if s else None):>9}{fmt(s.latency_p50_ms if s else None):>8}"
                f"{fmt(s.latency_p99_ms if s else None):>8}{(s.frames_in if s else 0):>8}{(s.frames_out if s else 0):>8}"
                f"{(s.drops if s else 0):>6}{(s.errors if s else 0):>5}{restarts:>9}"
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
        local = {p.name for p in self.supervisor.failed()}
        remote = {r.name for r in self.remote.values() if r.state == "failed" or (final and r.state == "lost")}
        return [name for name in self.graph.nodes if name in local or name in remote]

    def _tail(self, name: str) -> list[str]:
        return (self.remote[name].log_tail if name in self.remote else self.procs[name].log_tail)[-5:]

    # -- main loop ------------------------------------------------------------------------------------------------
    def run(self) -> int:
        session = (open_router(self.listen, self.security) if not self.connect
                   else open_client(self.connect, self.security))
        stop = threading.Event()

        def request_stop(signum: int, _frame: object) -> None:
            self.stop_reason = self.stop_reason or signal.Signals(signum).name
            stop.set()

        old = {s: signal.signal(s, request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
        agents = Agents(session, self.prefix, self.remote, self.lines, self.agent_timeout) if self.remote else None
        try:
            with session.declare_subscriber(keys.stats_key(self.prefix), self._on_stats), \
                    serve_schemas(session, self.prefix), agents or nullcontext():
                where = ", ".join(self.connect) if self.connect else f"embedded router on {', '.join(self.listen)}"
                self.out.write(f"mocapflow: running {self.graph.name!r} ({len(self.specs)} nodes, {where}, keys {self.prefix}/...)\n")
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
            for s, handler in old.items():
                signal.signal(s, handler)
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
            return 1
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
