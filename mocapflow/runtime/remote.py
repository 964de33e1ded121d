"""The launcher's side of the agent protocol (docs/lab-deployment.md): wait for the agents a graph places nodes on,
deploy, follow their reports, notice an agent lost, deploy again when it is back, and stop."""

from __future__ import annotations

import queue
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Self

import zenoh
from pydantic import TypeAdapter, ValidationError

from mocapflow.runtime.keys import agent_key, deploy_key, launcher_key, log_key, procs_key, stop_key
from mocapflow.runtime.protocol import AgentError, Deployment, Placement, ProcStatus
from mocapflow.runtime.supervisor import DRAIN_S, TERM_S
from mocapflow.runtime.worker import WorkerSpec

AGENT_GRACE_S = 5.0  # an agent's token may vanish this long (it rejoins a restarted router) before it counts as lost
DEPLOY_TIMEOUT_S = 10.0
STOP_TIMEOUT_S = DRAIN_S + 2 * TERM_S + 5.0
STATUS_LIST = TypeAdapter(list[ProcStatus])


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
            if reply.ok is None:
                continue
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
