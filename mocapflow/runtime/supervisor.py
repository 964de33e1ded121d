"""Supervision of worker processes: start, restart with backoff, give up, and stop in order.

Used by the launcher for the nodes it runs itself and by each agent for the nodes placed on its machine.
"""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import IO, Literal

from mocapflow.runtime.cpus import ONE_THREAD, assign_cores
from mocapflow.runtime.graph import Restart, RestartPolicy
from mocapflow.runtime.worker import EXIT_CONFIG, EXIT_FINISH, WorkerSpec

DRAIN_S = 10.0
TERM_S = 3.0
HEALTHY_S = 30.0

State = Literal["starting", "running", "restarting", "finished", "failed"]


@dataclass
class Proc:
    """One supervised node process and its history."""

    spec: WorkerSpec
    source: bool
    restart: Restart = "on-failure"  # the node's RestartPolicy
    max_restarts: int = RestartPolicy.model_fields["max_restarts"].default
    popen: subprocess.Popen[bytes] | None = None
    state: State = "starting"
    restarts: int = 0
    failures: int = 0
    next_start: float = 0.0
    started_at: float = 0.0
    exit_code: int | None = None
    log_tail: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return self.spec.node

    @property
    def pid(self) -> int | None:
        return self.popen.pid if self.popen else None


def place_on_cores(procs: list[Proc], out: IO[str], confine_caller: bool = False) -> None:
    """Give each process that asks for a core of its own (``cpu: own``) one, and the cores left to the others (and,
    with ``confine_caller``, to the calling thread and the threads it starts: the launcher's embedded router); say so
    in one line when the machine has no core to spare, and let every process share them all."""
    asks = {p.name: p.spec.cpu == "own" for p in procs}
    if not any(asks.values()):
        return
    placed = assign_cores(asks)
    if placed is None:
        out.write(f"mocapflow: {', '.join(name for name, own in asks.items() if own)}: no core of its own on this "
                  f"machine ({len(os.sched_getaffinity(0))} for {len(procs)} processes): all share them\n")
        return
    cores, shared = placed
    if confine_caller:
        os.sched_setaffinity(0, shared)
    for p in procs:
        p.spec = p.spec.model_copy(update={"cpus": cores[p.name]})


class Supervisor:
    """Runs a set of worker processes. Every line a worker prints, and every lifecycle event, goes to ``lines``."""

    def __init__(self, procs: list[Proc], lines: queue.Queue[str] | None = None) -> None:
        self.procs = {p.name: p for p in procs}
        self.lines: queue.Queue[str] = lines if lines is not None else queue.Queue()
        self.stopping = False

    def start(self) -> None:
        for proc in self.procs.values():
            self._spawn(proc)

    def _spawn(self, proc: Proc) -> None:
        proc.popen = subprocess.Popen(
            [sys.executable, "-m", "mocapflow.runtime.worker", proc.spec.model_dump_json()],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            env={**{var: "1" for var in ONE_THREAD}, **os.environ},
        )
        proc.state, proc.started_at, proc.exit_code = "running", time.monotonic(), None
        threading.Thread(target=self._pump, args=(proc, proc.popen.stdout), daemon=True).start()

    def _pump(self, proc: Proc, stream: IO[bytes]) -> None:
        for raw in stream:
            line = raw.decode(errors="replace").rstrip()
            proc.log_tail = (proc.log_tail + [line])[-20:]
            self.lines.put(f"[{proc.name}] {line}")

    def poll(self) -> None:
        """Notice exits; schedule restarts with exponential backoff; give up after ``max_restarts`` failures."""
        now = time.monotonic()
        for proc in self.procs.values():
            if proc.state == "restarting" and now >= proc.next_start and not self.stopping:
                self._spawn(proc)
                continue
            if proc.popen is None or proc.state != "running" or proc.popen.poll() is None:
                continue
            code = proc.exit_code = proc.popen.returncode
            if code == 0 or (self.stopping and code == -signal.SIGTERM):  # ended by a stop request, if still starting
                proc.state = "finished"
                continue
            if now - proc.started_at > HEALTHY_S:
                proc.failures = 0
            proc.failures += 1
            why = {EXIT_CONFIG: "configuration error", EXIT_FINISH: "finish failed: its output is lost"}.get(
                code, f"exit code {code}")
            if self.stopping or code in (EXIT_CONFIG, EXIT_FINISH) or proc.restart == "never" \
                    or proc.failures > proc.max_restarts:
                proc.state = "failed"
                self.lines.put(f"[{proc.name}] failed for good ({why})")
            else:
                delay = min(0.5 * 2 ** (proc.failures - 1), 10.0)
                proc.state, proc.next_start = "restarting", now + delay
                proc.restarts += 1
                self.lines.put(f"[{proc.name}] stopped ({why}); restart {proc.restarts} in {delay:.1f} s")

    def _waits(self) -> dict[str, set[str]]:
        """For each process, the others whose streams it waits for to end (its nodes' ``end_inputs``)."""
        owner = {node.node: p.name for p in self.procs.values() for node in p.spec.nodes()}
        return {p.name: {owner[up] for node in p.spec.nodes() for port in node.end_inputs or []
                         if (up := node.inputs[port].rsplit("/", 2)[-2]) in owner and owner[up] != p.name}
                for p in self.procs.values()}

    def _cut_off(self, waits: dict[str, set[str]]) -> dict[str, set[str]]:
        """The processes that failed or are restarting, and those that wait for a stream of one, directly or not
        (``waits``: ``_waits``): for each, the failed ones it waits for."""
        cut = {p.name: {p.name} for p in self.procs.values() if p.state in ("failed", "restarting")}
        grew = True
        while grew:
            grew = False
            for name, ups in waits.items():
                failed = set().union(*(cut[up] for up in ups if up in cut))
                if failed and not failed <= cut.get(name, set()):
                    cut[name] = cut.get(name, set()) | failed
                    grew = True
        return cut

    def alive(self) -> list[Proc]:
        return [p for p in self.procs.values() if p.popen is not None and p.popen.poll() is None]

    def all_finished(self) -> bool:
        return all(p.state == "finished" for p in self.procs.values())

    def failed(self) -> list[Proc]:
        return [p for p in self.procs.values() if p.state == "failed"]

    def _signal(self, procs: list[Proc], sig: int) -> None:
        for proc in procs:
            if proc.popen is not None and proc.popen.poll() is None:
                proc.popen.send_signal(sig)

    def shutdown(self, tick: Callable[[], None] = lambda: None) -> None:
        """Sources first, then let end-of-stream drain the graph, then terminate, then kill. ``tick`` runs while
        waiting (the launcher prints logs from it).

        A node that failed, or was restarting, sends no end of stream: the processes that wait for its stream, directly
        or not, would never drain. The drain waits for the others only, and says which are stopped without it."""
        self.stopping = True
        sources = [p for p in self.procs.values() if p.source]
        self._signal(sources, signal.SIGTERM)
        told: set[str] = set()
        waits = self._waits()
        for grace, sig in ((DRAIN_S, signal.SIGTERM), (TERM_S, signal.SIGKILL), (TERM_S, None)):
            deadline = time.monotonic() + grace
            while self.alive() and time.monotonic() < deadline:
                self.poll()
                tick()
                if sig == signal.SIGTERM:  # the drain
                    stuck = self._cut_off(waits)
                    for proc in self.alive():
                        if proc.name in stuck and proc.name not in told:
                            told.add(proc.name)
                            self.lines.put(f"[{proc.name}] stopped without the end of its input: "
                                           f"{', '.join(sorted(stuck[proc.name]))} failed")
                    if all(p.name in stuck for p in self.alive()):
                        break
                time.sleep(0.05)
            if sig is not None:
                self._signal(self.alive(), sig)
        for proc in self.procs.values():
            if proc.popen is not None:
                proc.popen.wait()
        self.poll()
