"""A lab on loopback: a router, two agents and a launcher as separate processes, all over real Zenoh.

Each node must run under the agent of its machine (its parent process), every frame must cross the router in order,
and the run must survive a node crash, a router restart and the loss of an agent.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import zenoh
from conftest import CLI

from mocapflow.errors import GraphError
from mocapflow.io.markers import read_markers
from mocapflow.mocap.simulator import Simulator, SimulatorConfig
from mocapflow.runtime.graph import load_graph, validate
from mocapflow.runtime.launcher import Launcher
from mocapflow.runtime.session import open_client

RATE = 240
MACHINES = ("capture", "workstation")
NODES = ("tracker", "hub", "recorder")
DEPLOYMENT = Path(__file__).resolve().parents[1] / "deployments" / "distributed-lab.yaml"


def cli(args: list[str], log: Path, cwd: Path) -> subprocess.Popen[bytes]:
    """A ``mocapflow`` process whose output goes to ``log`` (a pipe nobody reads could fill and block it)."""
    with log.open("wb") as out:
        return subprocess.Popen([*CLI, *args], cwd=cwd, stdout=out,
                                stderr=subprocess.STDOUT)


def wait_for(what: str, check: Callable[[], object], timeout: float = 60.0) -> object:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = check()
        if found:
            return found
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def stop(proc: subprocess.Popen[bytes], sig: int = signal.SIGTERM) -> None:
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def worker(node: str, prefix: str) -> tuple[int, int, dict] | None:
    """(pid, parent pid, WorkerSpec) of the live worker process of ``node`` in the run ``prefix``."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            argv = (entry / "cmdline").read_bytes().split(b"\0")
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        if len(argv) < 4 or argv[2] != b"mocapflow.runtime.worker":
            continue
        spec = json.loads(argv[3])
        state = stat.rsplit(")", 1)[1].split()
        if spec["node"] == node and spec["prefix"] == prefix and state[0] != "Z":
            return int(entry.name), int(state[1]), spec
    return None


def workers_of(prefix: str) -> list[str]:
    return [n for n in NODES if worker(n, prefix) is not None]


@dataclass
class Lab:
    """A router and one agent per machine, as separate processes on loopback."""

    tmp: Path
    endpoint: str
    router: subprocess.Popen[bytes] | None = None
    agents: dict[str, subprocess.Popen[bytes]] = field(default_factory=dict)

    def start_router(self) -> None:
        self.router = cli(["router", "--listen", self.endpoint], self.tmp / "router.log", self.tmp)
        wait_for("the router", lambda: "listening" in (self.tmp / "router.log").read_text(), timeout=60.0)

    def start_agent(self, name: str) -> None:
        log = self.tmp / f"agent-{name}.log"
        self.agents[name] = cli(["agent", "--name", name, "--connect", self.endpoint], log, self.tmp)
        # an agent compiles the numeric kernels before it is ready: on a fresh install half a minute on a quiet
        # machine, over a minute beside the other tests' processes
        wait_for(f"agent {name}", lambda: "ready" in log.read_text(), timeout=300.0)

    def graph(self, name: str, tracker: str, machines: tuple[str, str] = MACHINES) -> Path:
        """As deployments/distributed-lab.yaml, with a key prefix of its own: simulator -> relay -> recorder, the
        tracker on ``machines[0]``, the relay on ``machines[1]``, the recorder with the launcher."""
        path = self.tmp / f"{name}.yaml"
        path.write_text(f"""
name: {name}
nodes:
  tracker: {{plugin: simulator, config: {{rig: human, rate: {RATE}, seed: 3{tracker}}}, machine: {machines[0]}}}
  hub: {{plugin: relay, inputs: {{markers: tracker/markers}}, machine: {machines[1]}}}
  recorder: {{plugin: recorder, inputs: {{markers: hub/markers}}, config: {{path: {self.tmp / 'out.c3d'}}}}}
""")
        return path

    def run(self, graph: Path, *extra: str) -> subprocess.Popen[bytes]:
        return cli(["run", str(graph), "--connect", self.endpoint, *extra], self.tmp / "run.log", self.tmp)

    def log(self, name: str = "run") -> str:
        return (self.tmp / f"{name}.log").read_text()


@pytest.fixture
def lab(tmp_path: Path, free_endpoint: str) -> Iterator[Lab]:
    lab = Lab(tmp_path, free_endpoint)
    try:  # what started is stopped, also when a later start fails
        lab.start_router()
        for name in MACHINES:
            lab.start_agent(name)
        yield lab
    finally:
        for proc in [*lab.agents.values(), lab.router]:
            if proc is not None:
                stop(proc)


class FrameWatch:
    """Frame numbers seen on a key by an independent client of the router, with their arrival times."""

    def __init__(self, endpoint: str, key: str) -> None:
        self.frames: list[tuple[float, int]] = []
        self.lock = threading.Lock()
        self.session = open_client([endpoint])
        self.sub = self.session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            with self.lock:
                self.frames.append((time.monotonic(), json.loads(sample.payload.to_bytes())["frame"]))

    def flowing_since(self, t: float, count: int = RATE // 2) -> bool:
        """At least ``count`` frames arrived after ``t``, with increasing frame numbers."""
        with self.lock:
            after = [f for when, f in self.frames if when > t]
        return len(after) >= count and bool(np.all(np.diff(after) > 0))

    def close(self) -> None:
        self.session.close()


@pytest.mark.integration
def test_nodes_run_under_their_agents_and_every_frame_crosses_the_router(lab: Lab) -> None:
    frames = 3 * RATE + 1
    prefix = "mocapflow/lab"
    launcher = lab.run(DEPLOYMENT, "--set", f"recorder.path={lab.tmp / 'out.c3d'}", "--set", f"tracker.frames={frames}",
                       "--set", "tracker.seed=3", "--duration", "60")
    tracker, hub, recorder = (wait_for(node, lambda n=node: worker(n, prefix)) for node in NODES)
    assert tracker[1] == lab.agents["capture"].pid  # each node is a child of its machine's agent
    assert hub[1] == lab.agents["workstation"].pid
    assert recorder[1] == launcher.pid  # unplaced nodes run with the launcher
    for _pid, _ppid, spec in (tracker, hub, recorder):  # every session is a client of the lab's router
        assert spec["connect"] == [lab.endpoint]
    assert launcher.wait(timeout=60) == 0, lab.log()
    out = lab.log()
    assert "all nodes finished" in out and "MACHINE" in out
    assert "tracker       simulator           capture" in out and "hub           relay               workstation" in out
    data = read_markers(lab.tmp / "out.c3d")
    sim = Simulator(SimulatorConfig(rig="human", rate=RATE, seed=3, noise_mm=0.5))
    # Contiguous: one row per frame 0..frames-1, none missing, each equal to its own simulated frame.
    assert data.first_frame == 0 and data.positions.shape[0] == frames and not np.isnan(data.positions).any()
    truth = np.stack([sim.frame(i).points for i in range(0, frames, 29)])
    np.testing.assert_allclose(data.positions[::29], truth, atol=1e-3)
    assert not workers_of(prefix)
    assert all("stopped mocapflow/lab\n" in lab.log(f"agent-{m}") for m in MACHINES)


@pytest.mark.integration
def test_node_crash_router_restart_and_agent_loss(lab: Lab) -> None:
    prefix = "mocapflow/lab2"
    watch = FrameWatch(lab.endpoint, f"{prefix}/hub/markers")
    launcher = lab.run(lab.graph("lab2", ""))
    try:
        first = wait_for("hub", lambda: worker("hub", prefix))
        wait_for("frames", lambda: watch.flowing_since(0.0))

        # A node killed under its agent is restarted there, and the stream resumes.
        os.kill(first[0], signal.SIGKILL)
        t = time.monotonic()
        again = wait_for("a new hub", lambda: (w := worker("hub", prefix)) and w[0] != first[0] and w)
        assert again[1] == lab.agents["workstation"].pid
        wait_for("frames after the node restart", lambda: watch.flowing_since(t))
        restart = "[hub@workstation] stopped (exit code -9); restart 1"
        wait_for("the agent's log of the restart at the launcher", lambda: restart in lab.log())

        # The router restarts: every session rejoins it and the stream resumes.
        stop(lab.router, signal.SIGKILL)
        lab.start_router()
        t = time.monotonic()
        wait_for("frames after the router restart", lambda: watch.flowing_since(t))

        # An agent is lost: the run says so; when the agent is back its nodes are deployed again.
        stop(lab.agents["workstation"], signal.SIGKILL)
        wait_for("the loss reported", lambda: "agent workstation lost (nodes hub)" in lab.log())
        lab.start_agent("workstation")
        t = time.monotonic()
        wait_for("the hub deployed again", lambda: "agent workstation is back" in lab.log())
        wait_for("frames after the agent came back", lambda: watch.flowing_since(t))
    finally:
        watch.close()
        launcher.send_signal(signal.SIGINT)
        code = launcher.wait(timeout=60)
    out = lab.log()
    assert code == 0, out
    assert restart in out  # the agent's log reached the launcher, and stays in its output
    assert "stopped (SIGINT)" in out
    hub_row = next(line for line in out.splitlines()[::-1] if line.startswith("hub "))
    assert hub_row.split()[-1] == "2"  # restarted once by its agent, deployed again once on the new agent
    data = read_markers(lab.tmp / "out.c3d")
    recorded = ~np.isnan(data.positions[:, 0, 0])
    last = np.array([f for when, f in watch.frames if when > t]) - data.first_frame
    assert recorded[: RATE // 2].all() and not recorded.all()  # recorded from the start, with gaps during the faults
    assert recorded[last].all()  # and again once the agent was back, as far as the launcher's stop
    wait_for("every worker of the run to end", lambda: not workers_of(prefix), 60)  # the agents stop theirs too


@pytest.mark.integration
def test_missing_agents_are_named(tmp_path: Path, free_endpoint: str) -> None:
    lab = Lab(tmp_path, free_endpoint)
    lab.start_router()
    try:
        run = lab.run(lab.graph("lab3", "", ("nowhere", "elsewhere")), "--agent-timeout", "1")
        assert run.wait(timeout=30) == 2
    finally:
        stop(lab.router)
    out = lab.log()
    assert "no agent for machine(s) elsewhere, nowhere after 1 s" in out, out
    assert "tracker on nowhere" in out and "hub on elsewhere" in out


def test_placements_need_a_router(tmp_path: Path) -> None:
    path = tmp_path / "g.yaml"
    path.write_text("""
name: placed
nodes:
  tracker: {plugin: simulator, machine: cam}
  recorder: {plugin: recorder, inputs: {markers: tracker/markers}, config: {path: out.c3d}}
""")
    graph = load_graph(path)
    with pytest.raises(GraphError, match="tracker are placed on machines.*--connect"):
        Launcher(graph, validate(graph))
