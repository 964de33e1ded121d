"""Multi-process runs over real Zenoh on loopback: every frame, in order, restarts, clean stops, no orphans."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import ezc3d
import numpy as np
import orjson
import pytest
import zenoh
from conftest import CLI, graph_file

from mocapflow.messages import MarkerFrame
from mocapflow.mocap.simulator import Simulator, SimulatorConfig
from mocapflow.runtime.cpus import REALTIME_PRIORITY
from mocapflow.runtime.runner import Runner
from mocapflow.runtime.session import open_client

pytestmark = pytest.mark.integration  # every test here starts processes and Zenoh sessions

RATE = 240


def graph(tmp_path: Path, endpoint: str, extra_tracker: str = "", name: str = "rt") -> tuple[Path, str]:
    """A simulator -> recorder graph; its name (and key prefix) is unique to this test run."""
    return graph_file(tmp_path, name, endpoint, f"""
  tracker: {{plugin: simulator, config: {{rig: human, rate: {RATE}, seed: 3{extra_tracker}}}}}
  recorder: {{plugin: recorder, inputs: {{markers: tracker/markers}}, config: {{path: {tmp_path / 'out.c3d'}}}}}
""")


def start(args: list[str], cwd: Path) -> subprocess.Popen[str]:
    return subprocess.Popen([*CLI, *args], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def workers_of(prefix: str) -> list[int]:
    """PIDs of worker processes of one run, found by their command line: survivors here would be orphans."""
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                cmd = (entry / "cmdline").read_bytes().decode(errors="replace")
            except OSError:
                continue
            if "mocapflow.runtime.worker" in cmd and f'"prefix":"{prefix}"' in cmd:
                pids.append(int(entry.name))
    return pids


def worker_pid(prefix: str, node: str, timeout: float = 60.0) -> int:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for pid in workers_of(prefix):
            if f'"node":"{node}"' in Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace"):
                return pid
        time.sleep(0.1)
    raise AssertionError(f"no worker for {node}")


def wait_for_frames(endpoint: str, prefix: str, node: str, frames: int, timeout: float = 90.0) -> None:
    """Block until ``node`` reports having received ``frames`` input frames in its stats (handled, or passed over as
    a node that samples its input does)."""
    done = threading.Event()

    def on_stats(sample: zenoh.Sample) -> None:
        stats = orjson.loads(sample.payload.to_bytes())
        if stats["frames_in"] + stats["skipped"] >= frames:
            done.set()

    with open_client([endpoint]) as session, session.declare_subscriber(f"{prefix}/_stats/{node}", on_stats):
        assert done.wait(timeout), f"{node} did not reach {frames} frames"


def read_c3d(path: Path) -> tuple[np.ndarray, list[str], float, int]:
    c3d = ezc3d.c3d(str(path))
    points = c3d["data"]["points"][:3].transpose(2, 1, 0)  # (F, N, 3)
    labels = c3d["parameters"]["POINT"]["LABELS"]["value"]
    return points, labels, c3d["parameters"]["POINT"]["RATE"]["value"][0], c3d["header"]["points"]["first_frame"]


def test_every_frame_arrives_in_order_and_reads_back(tmp_path: Path, free_endpoint: str) -> None:
    frames = 5 * RATE + 1
    path, prefix = graph(tmp_path, free_endpoint, f", frames: {frames}")
    run = start(["run", str(path), "--duration", "60"], tmp_path)
    # Meanwhile, garbage on the recorder's input must be reported and must not disturb the stream.
    time.sleep(3)
    with open_client([free_endpoint]) as session:
        publisher = session.declare_publisher(f"{prefix}/tracker/markers")
        deadline = time.monotonic() + 10
        while not publisher.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.05)
        publisher.put(b'{"not": "a frame"}')
        time.sleep(0.5)
    out, _ = run.communicate(timeout=90)
    assert run.returncode == 0, out
    assert "all nodes finished" in out
    assert "invalid MarkerFrame" in out  # the malformed message was logged with its reason
    points, labels, rate, first = read_c3d(tmp_path / "out.c3d")
    sim = Simulator(SimulatorConfig(rig="human", rate=RATE, seed=3))
    assert points.shape[0] == frames and rate == RATE and labels == list(sim.rig.marker_labels)
    for i in (0, 1, frames // 2, frames - 1):
        np.testing.assert_allclose(points[i], sim.frame(i).points, atol=1e-3, equal_nan=True)
    # In order and complete: every frame's row matches its own simulated frame, none missing.
    truth = np.stack([sim.frame(i).points for i in range(0, frames, 37)])
    np.testing.assert_allclose(points[::37], truth, atol=1e-3, equal_nan=True)
    assert not workers_of(prefix)


def test_killed_node_is_restarted_and_the_stream_resumes(tmp_path: Path, free_endpoint: str) -> None:
    path, prefix = graph(tmp_path, free_endpoint, name="rk")
    run = start(["run", str(path), "--duration", "9"], tmp_path)
    victim = worker_pid(prefix, "tracker")
    wait_for_frames(free_endpoint, prefix, "recorder", RATE)
    os.kill(victim, signal.SIGKILL)
    t_kill = time.monotonic()
    replacement = worker_pid(prefix, "tracker")
    while replacement == victim and time.monotonic() - t_kill < 10:
        time.sleep(0.1)
        replacement = worker_pid(prefix, "tracker")
    assert replacement != victim
    out, _ = run.communicate(timeout=60)
    assert run.returncode == 0, out
    assert "restart 1" in out
    points, *_ = read_c3d(tmp_path / "out.c3d")
    seen = ~np.isnan(points[:, 0, 0])
    # frames flowed before the kill, stopped while the tracker was down, and flowed again after its restart:
    # exactly one gap, with frame numbers resuming on the tracker's clock
    edges = np.flatnonzero(np.diff(seen.astype(int)))
    assert len(edges) == 2 and seen[0] and seen[-1], edges
    assert edges[0] + 1 >= RATE and len(seen) - edges[1] - 1 > RATE
    assert not workers_of(prefix)


def test_interrupt_stops_cleanly_and_writes_the_recording(tmp_path: Path, free_endpoint: str) -> None:
    path, prefix = graph(tmp_path, free_endpoint, name="ri")
    run = start(["run", str(path)], tmp_path)
    wait_for_frames(free_endpoint, prefix, "recorder", 2 * RATE)
    run.send_signal(signal.SIGINT)
    out, _ = run.communicate(timeout=30)
    assert run.returncode == 0, out
    assert "stopped (SIGINT)" in out
    points, *_ = read_c3d(tmp_path / "out.c3d")
    assert points.shape[0] >= 2 * RATE and not np.isnan(points).any()
    assert not workers_of(prefix)


def test_node_failing_for_good_makes_the_run_fail(tmp_path: Path, free_endpoint: str) -> None:
    path, prefix = graph(tmp_path, free_endpoint, f", bvh: {tmp_path / 'missing.bvh'}", name="rf")
    run = start(["run", str(path), "--duration", "30"], tmp_path)
    out, _ = run.communicate(timeout=60)
    assert run.returncode == 2, out  # refused its configuration: exit code 2
    assert "failed: tracker" in out and "missing.bvh" in out
    assert not workers_of(prefix)


def test_a_port_in_use_is_one_line_naming_it(tmp_path: Path, free_endpoint: str) -> None:
    import socket

    host, port = free_endpoint.removeprefix("tcp/").rsplit(":", 1)
    with socket.socket() as taken:
        taken.bind((host, int(port)))
        taken.listen()
        path, prefix = graph(tmp_path, free_endpoint, name="busy")
        run = start(["run", str(path), "--duration", "5"], tmp_path)
        out, _ = run.communicate(timeout=60)
    assert run.returncode == 2, out
    assert f"{free_endpoint}: address already in use" in out and "--listen" in out and "Traceback" not in out
    assert not workers_of(prefix)


def test_introspection_commands_see_a_live_run(tmp_path: Path, free_endpoint: str) -> None:
    path, prefix = graph(tmp_path, free_endpoint, name="rn")
    run = start(["run", str(path), "--duration", "120"], tmp_path)
    try:
        worker_pid(prefix, "recorder")
        time.sleep(2)
        cli = CLI
        nodes = subprocess.run([*cli, "nodes", "--connect", free_endpoint, "--prefix", prefix, "--timeout", "30"],
                               capture_output=True, text=True, timeout=90)
        assert f"{prefix}/tracker" in nodes.stdout and f"{prefix}/recorder" in nodes.stdout, nodes.stdout
        echo = subprocess.run([*cli, "echo", f"{prefix}/tracker/markers", "-n", "2", "--connect", free_endpoint,
                               "--timeout", "30"],
                              capture_output=True, text=True, timeout=90)
        assert echo.stdout.count("application/json;mocapflow/MarkerFrame") == 2 and "positions:" in echo.stdout
        hz = subprocess.run([*cli, "hz", f"{prefix}/tracker/markers", "-n", "1", "--window", "2", "--connect",
                             free_endpoint, "--timeout", "30"], capture_output=True, text=True, timeout=90)
        # the rate itself depends on how busy the machine is: only that messages were counted and timed is checked
        assert hz.returncode == 0 and hz.stdout.startswith(f"{prefix}/tracker/markers: "), hz.stdout
        assert int(hz.stdout.split("n=")[1].split(")")[0]) > 1 and float(hz.stdout.split(": ")[1].split()[0]) > 0
        with open_client([free_endpoint]) as session:
            replies = list(session.get(f"{prefix}/_schema/MarkerFrame", timeout=5))
        assert replies and b'"$id":"mocapflow/MarkerFrame"' in replies[0].ok.payload.to_bytes()
    finally:
        run.send_signal(signal.SIGINT)
        out, _ = run.communicate(timeout=60)
    assert run.returncode == 0, out


def test_model_reaches_a_node_that_starts_late(tmp_path: Path, free_endpoint: str) -> None:
    """The joint estimator publishes its skeleton once; a skeleton publisher restarted later still receives it from
    the model cache and goes on posing every frame. (14 s of stream: a restart on a machine busy with other work took
    more than the 6 s that 8 s left it.)"""
    from mocapflow.mocap.simulator import simulate, truth_skeleton

    sim = Simulator(SimulatorConfig(rig="rods", rate=RATE, seed=3))
    reference = simulate(SimulatorConfig(rig="rods", rate=RATE, seed=3, noise_mm=0.0), 1).true_positions[0]
    skeleton_file = tmp_path / "rods.json"
    skeleton_file.write_text(truth_skeleton(sim.rig, reference).model_dump_json())
    path, prefix = graph_file(tmp_path, "late", free_endpoint, f"""
  tracker: {{plugin: simulator, config: {{rig: rods, rate: {RATE}, seed: 3, frames: {14 * RATE}}}}}
  joints: {{plugin: joints-closed-form, inputs: {{markers: tracker/markers}},
            config: {{skeleton: {skeleton_file}, refine: false}}}}
  skeleton: {{plugin: skeleton, inputs: {{markers: tracker/markers, skeleton: joints/skeleton}}}}
  recorder: {{plugin: recorder, inputs: {{markers: tracker/markers, pose: skeleton/pose}},
              config: {{path: {tmp_path / 'late.c3d'}}}}}
""")
    run = start(["run", str(path)], tmp_path)
    wait_for_frames(free_endpoint, prefix, "skeleton", 2 * RATE)
    os.kill(worker_pid(prefix, "skeleton"), signal.SIGKILL)
    out, _ = run.communicate(timeout=60)
    assert run.returncode == 0, out
    assert "[skeleton] stopped" in out and "restart 1" in out
    c3d = ezc3d.c3d(str(tmp_path / "late.c3d"))
    labels = c3d["parameters"]["POINT"]["LABELS"]["value"]
    joint = c3d["data"]["points"][:3, labels.index(sim.joint_names[0])].T  # (F, 3)
    posed = ~np.isnan(joint[:, 0])
    # posed before the kill (from the frame after the model was published), not while the node was down, and again
    # after its restart, to the last frame
    runs = np.split(posed, np.flatnonzero(np.diff(posed.astype(int))) + 1)
    posed_runs = [len(r) for r in runs if r[0]]
    assert posed[-1] and len(posed_runs) == 2 and posed_runs[0] > RATE and posed_runs[1] > RATE, posed_runs
    truth = np.stack([sim.frame(i).joint_centres[0] for i in range(len(joint))])
    assert np.nanmax(np.linalg.norm(joint - truth, axis=1)) < 5.0


def test_cores_of_their_own_go_to_the_processes_that_ask_while_one_is_left_for_the_others() -> None:
    from mocapflow.runtime.cpus import assign_cores

    assert assign_cores({"tracker": False, "frame": True, "joints": False}, {0, 1}) == (
        {"tracker": [0], "frame": [1], "joints": [0]}, [0])
    assert assign_cores({"a": True, "b": True, "c": False}, {0, 1, 2, 3}) == (
        {"a": [3], "b": [2], "c": [0, 1]}, [0, 1])
    assert assign_cores({"a": True, "b": True}, {0, 1}) is None  # none would be left for the rest
    assert assign_cores({"a": False}, {0, 1}) is None  # nobody asks


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="a core of its own needs two cores")
def test_a_node_that_asks_runs_on_a_core_of_its_own(tmp_path: Path, free_endpoint: str) -> None:
    """A group with a member that asks for a core of its own runs on one core, every other process of the graph
    (the launcher's too) on the others."""
    path, prefix = graph_file(tmp_path, "cpu", free_endpoint, f"""
  tracker: {{plugin: simulator, config: {{rig: rods, rate: {RATE}, seed: 3}}}}
  relay: {{plugin: relay, inputs: {{markers: tracker/markers}}, group: pair, cpu: own}}
  recorder: {{plugin: recorder, inputs: {{markers: relay/markers}}, config: {{path: {tmp_path / 'o.c3d'}}},
             group: pair}}
""")
    run = start(["run", str(path), "--duration", "60"], tmp_path)
    try:
        wait_for_frames(free_endpoint, prefix, "recorder", RATE)

        def cores(pid: int) -> set[frozenset[int]]:  # the core sets of the process's threads
            return {frozenset(os.sched_getaffinity(int(task.name))) for task in Path(f"/proc/{pid}/task").iterdir()}

        pair, tracker = cores(worker_pid(prefix, "pair")), cores(worker_pid(prefix, "tracker"))
        launcher_main = frozenset(os.sched_getaffinity(run.pid))
    finally:
        run.send_signal(signal.SIGINT)
        out, _ = run.communicate(timeout=60)
    assert run.returncode == 0, out
    (own,) = pair
    assert len(own) == 1 and len(tracker) == 1 and not own & next(iter(tracker)), (pair, tracker)
    assert launcher_main == next(iter(tracker))


def test_a_node_runs_at_the_niceness_its_graph_sets(tmp_path: Path, free_endpoint: str) -> None:
    """A node runs at the niceness its graph sets, the others at 0; a group at its most favoured member's. A node
    with 'cpu: idle' runs on CPU time nothing else wants (SCHED_IDLE); one with 'cpu: realtime', and a group one of
    whose members asks, at a real-time priority (SCHED_FIFO) where this machine gives the right to, else as any
    other, saying so. Every node process runs BLAS on one thread, whose spinning helpers would take CPU from the
    other processes."""
    path, prefix = graph_file(tmp_path, "nc", free_endpoint, f"""
  tracker: {{plugin: simulator, config: {{rig: rods, rate: {RATE}, seed: 3}}, cpu: realtime}}
  clusterer: {{plugin: clusterer-spectral, inputs: {{markers: tracker/markers}}, nice: 10}}
  relay: {{plugin: relay, inputs: {{markers: tracker/markers}}, nice: 4, cpu: idle}}
  other: {{plugin: relay, inputs: {{markers: relay/markers}}, nice: 12, group: pair, cpu: idle}}
  recorder: {{plugin: recorder, inputs: {{markers: other/markers}}, config: {{path: {tmp_path / 'o.c3d'}}},
             group: pair, cpu: realtime}}
""")
    fifo = f"import os; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param({REALTIME_PRIORITY}))"
    allowed = subprocess.run([sys.executable, "-c", fifo], capture_output=True, check=False).returncode == 0
    run = start(["run", str(path), "--duration", "60"], tmp_path)
    pids: dict[str, int] = {}
    try:
        def on_stats(sample: zenoh.Sample) -> None:
            stats = orjson.loads(sample.payload.to_bytes())
            pids[stats["node"]] = stats["pid"]

        with open_client([free_endpoint], timeout=60) as session, \
                session.declare_subscriber(f"{prefix}/_stats/*", on_stats):
            wait_for_frames(free_endpoint, prefix, "recorder", RATE)
            deadline = time.monotonic() + 60
            while len(pids) < 5 and time.monotonic() < deadline:  # every node's statistics, with its PID
                time.sleep(0.2)
            stat = {node: Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
                    for node, pid in dict(pids).items()}
            nice = {node: int(fields[16]) for node, fields in stat.items()}
            idle = {node for node, fields in stat.items() if int(fields[38]) == os.SCHED_IDLE}
            realtime = {node: int(fields[37]) for node, fields in stat.items() if int(fields[38]) == os.SCHED_FIFO}
            blas = {node: dict(v.split("=", 1) for v in Path(f"/proc/{pid}/environ").read_text().split("\0")
                               if v.startswith("OPENBLAS_NUM_THREADS="))
                    for node, pid in dict(pids).items()}
    finally:
        run.send_signal(signal.SIGINT)
        out, _ = run.communicate(timeout=60)
    assert nice == {"tracker": 0, "clusterer": 10, "relay": 4, "other": 0, "recorder": 0}, (nice, out)
    assert idle == {"relay"}, idle  # 'cpu: idle'; a group only when all its members ask
    if allowed:  # 'cpu: realtime', at its priority; a group when one of its members asks
        assert realtime == dict.fromkeys(("tracker", "other", "recorder"), REALTIME_PRIORITY), realtime
    else:
        assert realtime == {}, realtime
        assert out.count("'cpu: realtime' needs Linux and the right to real-time priority") == 2, out  # tracker, group
    one = os.environ.get("OPENBLAS_NUM_THREADS", "1")  # the setting of whoever runs the graph, else one thread
    assert all(env == {"OPENBLAS_NUM_THREADS": one} for env in blas.values()), blas


@pytest.mark.integration
def test_a_paced_source_is_asked_to_prepare_each_frame_only_before_it_is_emitted(tmp_path: Path,
                                                                                   free_endpoint: str) -> None:
    """``Node.prepare(i)`` comes after frame i - 1 was emitted and handled and before frame i is: never for a frame
    already emitted (after the last frame, once: the source tells its end only when asked for the frame past it)."""
    calls = tmp_path / "calls.txt"
    sink = tmp_path / "sink.txt"
    path = tmp_path / "g.yaml"
    path.write_text(
        f"name: prepare\nzenoh: {{listen: ['{free_endpoint}']}}\nnodes:\n"
        f"  source: {{plugin: 'prepared_source:PreparedSource', group: g,\n"
        f"           config: {{path: '{calls}', rate: 20, frames: 30}}}}\n"
        f"  sink: {{plugin: 'slow_sink:SlowSink', group: g, inputs: {{markers: source/markers}},\n"
        f"          config: {{path: '{sink}', delay_s: 0}}}}\n"
    )
    tests = str(Path(__file__).resolve().parent)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [tests, os.environ.get("PYTHONPATH")]))}
    run = subprocess.run([*CLI, "run", str(path)], capture_output=True, text=True, timeout=90, env=env, check=False)
    assert run.returncode == 0, run.stdout + run.stderr
    log = [line.split() for line in calls.read_text().split("\n") if line]
    assert [int(n) for kind, n in log if kind == "emit"] == list(range(30))
    assert [int(n) for n in sink.read_text().split()] == list(range(30))
    emitted = -1
    for kind, n in log:
        if kind == "emit":
            emitted = int(n)
        else:
            assert int(n) == emitted + 1, log  # the next frame, after the last one emitted
    assert [int(n) for kind, n in log if kind == "prepare"] == list(range(1, 31))  # after every frame


def test_a_failing_prepare_is_reported_and_costs_nothing_else(tmp_path: Path) -> None:
    from prepared_source import PreparedSource

    class Failing(PreparedSource):
        def prepare(self, index: int) -> None:
            raise ValueError("no block")

    sent: list[MarkerFrame] = []
    runner = Runner("source", Failing, Failing.Config(path=str(tmp_path / "calls.txt")),
                    lambda port, message: sent.append(message), set())
    runner.prepare(3)
    assert runner.stats.errors == 1 and runner.stats.last_error == "prepare frame 3: no block"
    assert runner.emit(0) and [m.frame for m in sent] == [0]
