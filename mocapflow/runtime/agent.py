"""Agents: one per machine, running the nodes that graphs place on that machine (``machine: NAME``).

An agent is a Zenoh client of the lab's router and speaks with launchers over Zenoh only (docs/lab-deployment.md):

- ``mocapflow/_agents/{name}``: liveliness token held while the agent runs; launchers wait for it.
- ``mocapflow-control/agents/{name}/deploy``: queryable (control keys live outside ``mocapflow/**``, so read-only
  roles of the data do not reach them); the query payload is a ``Deployment`` (JSON: run id, key prefix,
  each node's WorkerSpec and restart policy). The agent starts the nodes under a ``Supervisor`` and replies with
  their ``ProcStatus`` list, or with an error (plugin missing here, prefix busy with another run). Deploying a run
  the agent already runs is answered with its current state, so a launcher may repeat a deployment safely.
- ``mocapflow-control/agents/{name}/stop``: queryable; payload ``{"run": ID}``. The agent stops that run's nodes in
  order (sources first, drain, terminate, kill) and replies with their final ``ProcStatus`` list.
- ``{prefix}/_procs/{node}``: the ``ProcStatus`` of each node it runs, on every change and every second.
- ``{prefix}/_log/{name}``: every line its nodes print, as ``[node] text``.
- ``{prefix}/_launcher/{run}``: the launcher's liveliness token. A run whose launcher has been gone for
  ``LAUNCHER_GRACE_S`` while the agent itself reaches the router is stopped, so no node outlives its launcher.

Nodes are started from the agent's main thread: each worker dies with the thread that forked it (PR_SET_PDEATHSIG),
so killing an agent ends its nodes too.
"""

from __future__ import annotations

import logging
import queue
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import zenoh
from pydantic import ValidationError

from mocapflow.mocap.compiled import compile_all
from mocapflow.runtime.kernels import compile_kernels
from mocapflow.runtime.keys import (
    agent_key,
    deploy_key,
    launcher_key,
    log_key,
    procs_key,
    stop_key,
)
from mocapflow.runtime.plugins import PluginNotFound, load
from mocapflow.runtime.protocol import Deployment, ProcStatus, keep_clock_origin
from mocapflow.runtime.session import open_client
from mocapflow.runtime.signals import stop_on_signals
from mocapflow.runtime.supervisor import Proc, Supervisor, place_on_cores

STATUS_PERIOD_S = 1.0
LAUNCHER_GRACE_S = 5.0

log = logging.getLogger("mocapflow.agent")


@dataclass
class Run:
    """One launcher's nodes on this agent."""

    deployment: Deployment
    supervisor: Supervisor
    launcher_present: bool = False
    launcher_absent_since: float | None = None
    stopper: threading.Thread | None = None
    done: threading.Event = field(default_factory=threading.Event)
    published: dict[str, tuple[Any, ...]] = field(default_factory=dict)
    last_publish: float = 0.0
    declared: list[Any] = field(default_factory=list)


class Agent:
    """Runs, supervises and stops the nodes that launchers deploy on machine ``name``."""

    def __init__(self, name: str, connect: list[str], security: Path | None = None,
                 out: IO[str] = sys.stdout, timeout: float | None = None) -> None:
        self.name = name
        self.connect = connect
        self.security = security
        self.out = out
        self.runs: dict[str, Run] = {}  # by key prefix: one run per prefix on an agent
        self.session = open_client(connect, security, timeout)

    def say(self, text: str) -> None:
        self.out.write(f"agent {self.name}: {text}\n")
        self.out.flush()

    # -- protocol -------------------------------------------------------------------------------------------------
    def statuses(self, run: Run) -> list[ProcStatus]:
        return [
            ProcStatus(run=run.deployment.run, node=p.name, machine=self.name, state=p.state, pid=p.pid,
                       restarts=p.restarts, exit_code=p.exit_code)
            for p in run.supervisor.procs.values()
        ]

    def _reply(self, query: zenoh.Query, key: str, run: Run) -> None:
        payload = "[" + ",".join(s.model_dump_json() for s in self.statuses(run)) + "]"
        query.reply(key, payload, encoding=zenoh.Encoding.APPLICATION_JSON)

    def deploy(self, query: zenoh.Query) -> None:
        """Start a deployment's nodes, or report the state of a run already deployed here."""
        try:
            deployment = Deployment.model_validate_json(query.payload.to_bytes() if query.payload else b"")
        except ValidationError as exc:
            query.reply_err(f"agent {self.name}: invalid deployment: {exc.errors()[0]['msg']}")
            return
        existing = self.runs.get(deployment.prefix)
        if existing is not None:
            if existing.deployment.run != deployment.run:
                query.reply_err(f"agent {self.name} already runs {deployment.prefix} for another launcher")
            elif existing.stopper is not None:
                query.reply_err(f"agent {self.name} is stopping {deployment.prefix}")
            else:
                self._reply(query, deploy_key(self.name), existing)
            return
        for placement in deployment.nodes:  # the plugins installed here may differ from the launcher's
            try:
                load(placement.spec.plugin).Config.model_validate(placement.spec.config)
            except (PluginNotFound, ValidationError) as exc:
                query.reply_err(f"agent {self.name}: node {placement.spec.node}: {exc}")
                return
        security = str(self.security) if self.security else None
        procs = [
            Proc(spec=p.spec.model_copy(update={"connect": self.connect, "security": security}), source=p.source,
                 restart=p.restart, max_restarts=p.max_restarts)
            for p in deployment.nodes
        ]
        place_on_cores(procs, sys.stdout)
        run = Run(deployment, Supervisor(procs))
        specs = {p.name: p.spec for p in procs}

        def on_launcher(sample: zenoh.Sample) -> None:
            run.launcher_present = sample.kind == zenoh.SampleKind.PUT

        run.declared = [
            self.session.declare_subscriber(f"{deployment.prefix}/_stats/*",
                                            lambda sample: keep_clock_origin(specs, sample)),
            self.session.liveliness().declare_subscriber(launcher_key(deployment.prefix, deployment.run),
                                                         on_launcher, history=True),
        ]
        run.launcher_absent_since = time.monotonic()  # the launcher's token is announced shortly
        run.supervisor.start()
        self.runs[deployment.prefix] = run
        self.say(f"started {', '.join(specs)} of {deployment.prefix} (run {deployment.run})")
        self._reply(query, deploy_key(self.name), run)

    def stop(self, run: Run, query: zenoh.Query | None, why: str) -> None:
        """Stop a run's nodes in order on a thread of its own (no node is started while stopping), then answer."""
        first = run.stopper is None

        def stop_run() -> None:
            if first:
                run.supervisor.shutdown()
            else:  # already stopping: answer once that is done
                run.done.wait()
            if query is not None:
                self._reply(query, stop_key(self.name), run)
            if first:
                run.done.set()

        thread = threading.Thread(target=stop_run, name=f"stop {run.deployment.prefix}", daemon=True)
        if first:
            self.say(f"stopping {run.deployment.prefix} ({why})")
            run.stopper = thread
        if first or query is not None:
            thread.start()

    def on_stop(self, query: zenoh.Query) -> None:
        wanted = query.payload.to_string() if query.payload else ""
        run = next((r for r in self.runs.values() if r.deployment.run == wanted), None)
        if run is None:  # not (or no longer) running here: nothing to stop
            query.reply(stop_key(self.name), "[]", encoding=zenoh.Encoding.APPLICATION_JSON)
            return
        self.stop(run, query, "the launcher asked")

    # -- main loop ------------------------------------------------------------------------------------------------
    def _publish(self, run: Run, now: float, force: bool = False) -> None:
        prefix = run.deployment.prefix
        while True:
            try:
                line = run.supervisor.lines.get_nowait()
            except queue.Empty:
                break
            self.out.write(f"{prefix} {line}\n")
            self.session.put(log_key(prefix, self.name), line, encoding=zenoh.Encoding.TEXT_PLAIN)
        periodic = force or now - run.last_publish >= STATUS_PERIOD_S
        for status in self.statuses(run):
            seen = (status.state, status.pid, status.restarts, status.exit_code)
            if periodic or run.published.get(status.node) != seen:
                run.published[status.node] = seen
                self.session.put(procs_key(prefix, status.node), status.model_dump_json(),
                                 encoding=zenoh.Encoding.APPLICATION_JSON)
        if periodic:
            run.last_publish = now
        self.out.flush()

    def _watch_launcher(self, run: Run, now: float, connected: bool) -> None:
        """Stop a run whose launcher is gone; while the router itself is unreachable nobody is to blame."""
        if run.launcher_present or not connected:
            run.launcher_absent_since = None
            return
        if run.launcher_absent_since is None:
            run.launcher_absent_since = now
        elif now - run.launcher_absent_since > LAUNCHER_GRACE_S:
            self.stop(run, None, f"its launcher has been gone for {LAUNCHER_GRACE_S:.0f} s")

    def _forget(self, prefix: str) -> None:
        run = self.runs.pop(prefix)
        self._publish(run, time.monotonic(), force=True)  # last lines and final states
        for declared in run.declared:
            declared.undeclare()
        self.say(f"stopped {prefix}")

    def serve(self, stop: threading.Event) -> None:
        """Announce this agent and serve deployments until ``stop`` is set; then stop every run in order."""
        try:
            deploys = self.session.declare_queryable(deploy_key(self.name))
            stops = self.session.declare_queryable(stop_key(self.name))
            token = self.session.liveliness().declare_token(agent_key(self.name))
            self.say(f"ready (connected to {', '.join(self.connect)})")
            while not stop.wait(0.05):
                while (query := deploys.try_recv()) is not None:
                    self.deploy(query)
                while (query := stops.try_recv()) is not None:
                    self.on_stop(query)
                now = time.monotonic()
                connected = bool(self.session.info.routers_zid())
                for prefix, run in list(self.runs.items()):
                    if run.stopper is None:
                        run.supervisor.poll()
                        self._watch_launcher(run, now, connected)
                    self._publish(run, now)
                    if run.done.is_set():
                        self._forget(prefix)
            for run in self.runs.values():
                self.stop(run, None, "the agent is stopping")
            for prefix, run in list(self.runs.items()):
                while not run.done.wait(0.05):
                    self._publish(run, time.monotonic())
                self._forget(prefix)
            token.undeclare()
        finally:
            self.session.close()


def run_agent(name: str, connect: list[str], security: Path | None = None, timeout: float | None = None) -> int:
    """Serve as agent ``name`` until SIGINT or SIGTERM."""
    print(f"agent {name}: joining {', '.join(connect)}", flush=True)
    signal.signal(signal.SIGINT, signal.SIG_DFL)  # until the router answers, Ctrl-C simply ends the agent
    compile_kernels(sys.stdout, compile_all)  # whichever nodes it will be asked to run
    agent = Agent(name, connect, security, timeout=timeout)
    stop = threading.Event()
    with stop_on_signals(stop):
        agent.serve(stop)
    return 0
