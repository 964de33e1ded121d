"""Node groups over real Zenoh: a grouped graph gives the ungrouped graph's output bit for bit, every frame in order;
outside subscribers still see every output of the group; a killed group process restarts as one and the stream
resumes; ``validate`` checks groups."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import orjson
import pytest
import zenoh
from conftest import CLI, run_cli
from test_runtime import read_c3d, wait_for_frames, worker_pid, workers_of

from mocapflow.errors import GraphError
from mocapflow.io.markers import read_markers, write_markers
from mocapflow.runtime.graph import load_graph
from mocapflow.runtime.session import open_router


def replay_graph(tmp_path: Path, endpoint: str, name: str, source: Path, group: str | None) -> Path:
    """A real capture replayed (four times its rate) through the occlusion filler to a recording; ``group`` puts
    the three nodes in one process."""
    g = f", group: {group}" if group else ""
    path = tmp_path / f"{name}.yaml"
    path.write_text(
        f"name: {name}\nnodes:\n"
        f"  tracker: {{plugin: c3d-replay, config: {{path: '{source}', speed: 4}}{g}}}\n"
        f"  filler: {{plugin: occlusion-filler, inputs: {{markers: tracker/markers}}{g}}}\n"
        f"  recorder: {{plugin: recorder, inputs: {{markers: filler/markers}},"
        f" config: {{path: '{tmp_path / name}.c3d'}}{g}}}\n"
    )
    return path


@pytest.mark.integration
def test_grouped_replay_equals_ungrouped_and_outside_subscribers_see_every_output(
        tmp_path: Path, free_endpoint: str, data_dir: Path) -> None:
    data = read_markers(data_dir / "lowerbody_clusters_knee_0401.c3d")
    rows = slice(1000, 1300)
    positions = data.positions[rows].copy()
    positions[100:160, data.labels.index("LTH2")] = np.nan  # a gap for the filler to fill
    source = tmp_path / "slice.c3d"
    write_markers(source, type(data)(positions, data.labels, data.rate, data.first_frame + rows.start))
    frames = rows.stop - rows.start

    seen: dict[str, list[int]] = {"filler/markers": [], "filler/predictions": [], "tracker/markers": []}
    outputs = {}
    with open_router([free_endpoint]) as router:
        for name, group in (("flat", None), ("grouped", "pipeline")):
            subs = []
            if group:
                def listener(key: str):  # noqa: ANN202
                    def on_sample(sample: zenoh.Sample) -> None:
                        if sample.kind == zenoh.SampleKind.PUT:
                            seen[key].append(orjson.loads(sample.payload.to_bytes())["frame"])
                    return on_sample
                subs = [router.declare_subscriber(f"mocapflow/{name}/{key}", listener(key)) for key in seen]
            graph = replay_graph(tmp_path, free_endpoint, name, source, group)
            done = run_cli("run", graph, "--connect", free_endpoint, "--summary", tmp_path / f"{name}.json",
                           timeout=120)
            assert done.returncode == 0, done.stdout + done.stderr
            time.sleep(0.3)
            for sub in subs:
                sub.undeclare()
            outputs[name] = read_markers(tmp_path / f"{name}.c3d")
            stats = orjson.loads((tmp_path / f"{name}.json").read_bytes())
            assert all(n["drops"] == 0 and n["errors"] == 0 for n in stats.values()), stats
            if group:
                assert len({n["pid"] for n in stats.values()}) == 1  # one process
    flat, grouped = outputs["flat"], outputs["grouped"]
    assert flat.positions.shape[0] == frames and np.isfinite(flat.positions[100:160, data.labels.index("LTH2")]).any()
    assert grouped.labels == flat.labels and grouped.first_frame == flat.first_frame
    np.testing.assert_array_equal(grouped.positions, flat.positions)
    np.testing.assert_array_equal(grouped.flags, flat.flags)
    first = data.first_frame + rows.start
    for key, got in seen.items():  # published for the outside subscriber although no node outside the group needs it
        want = list(range(first + 1, first + frames + 1)) if key.endswith("predictions") else \
            list(range(first, first + frames))
        assert got == want, (key, got[:5], len(got))


@pytest.mark.integration
def test_killed_group_restarts_as_one_and_the_stream_resumes(tmp_path: Path, free_endpoint: str) -> None:
    rate = 60
    prefix = "mocapflow/gk"
    path = tmp_path / "gk.yaml"
    path.write_text(
        f"name: gk\nzenoh: {{listen: ['{free_endpoint}']}}\nnodes:\n"
        f"  tracker: {{plugin: simulator, config: {{rig: rods, rate: {rate}, seed: 3}}}}\n"
        "  relay: {plugin: relay, inputs: {markers: tracker/markers}, group: sink}\n"
        f"  recorder: {{plugin: recorder, inputs: {{markers: relay/markers}}, group: sink,"
        f" config: {{path: '{tmp_path / 'out.c3d'}'}}}}\n"
    )
    run = subprocess.Popen([*CLI, "run", str(path), "--duration", "9"], cwd=tmp_path, stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, text=True)
    try:
        wait_for_frames(free_endpoint, prefix, "recorder", rate)
        victim = worker_pid(prefix, "recorder")
        assert worker_pid(prefix, "relay") == victim  # both nodes in the one process
        os.kill(victim, signal.SIGKILL)
        t_kill = time.monotonic()
        replacement = victim
        while replacement == victim and time.monotonic() - t_kill < 15:
            time.sleep(0.1)
            replacement = worker_pid(prefix, "recorder")
        assert replacement != victim
        out, _ = run.communicate(timeout=60)
    finally:
        if run.poll() is None:
            run.kill()
            run.wait()
    assert run.returncode == 0, out
    assert "[sink] stopped (exit code -9); restart 1" in out, out
    points, *_ = read_c3d(tmp_path / "out.c3d")
    seen = ~np.isnan(points[:, 0, 0])
    edges = np.flatnonzero(np.diff(seen.astype(int)))
    assert len(edges) == 2 and seen[0] and seen[-1], edges  # one gap while the group was down, frames after it
    assert len(seen) - edges[1] - 1 > rate
    assert not workers_of(prefix)


def test_validate_checks_groups(tmp_path: Path) -> None:
    path = tmp_path / "g.yaml"
    path.write_text("name: g\nnodes:\n  a: {plugin: simulator, group: one}\n  b: {plugin: simulator, group: one}\n"
                    "  c: {plugin: relay, inputs: {markers: a/markers}, group: a}\n")
    with pytest.raises(GraphError) as err:
        load_graph(path)
    assert "group 'one' has 2 sources (a, b): one at most" in str(err.value)
    assert "group 'a' has the name of another node" in str(err.value)
    path.write_text("name: g\nnodes:\n  a: {plugin: simulator, group: one}\n"
                    "  c: {plugin: relay, inputs: {markers: a/markers}, group: one, machine: lab2}\n")
    with pytest.raises(GraphError, match="group 'one' has nodes placed on machines \\(c\\)"):
        load_graph(path)


@pytest.mark.integration
def test_an_output_nobody_reads_is_left_out_until_someone_subscribes(tmp_path: Path, free_endpoint: str) -> None:
    """The simulator builds its truth only for a reader (``Node.listened``): without one it publishes its markers
    alone; a subscriber from outside the graph gets every frame's truth."""
    frames = 120
    graph = tmp_path / "truth.yaml"
    graph.write_text(
        "name: truth\nnodes:\n"
        f"  tracker: {{plugin: simulator, group: g, config: {{rig: human, rate: 60, frames: {frames}}}}}\n"
        f"  recorder: {{plugin: recorder, group: g, inputs: {{markers: tracker/markers}},"
        f" config: {{path: '{tmp_path / 'out.c3d'}'}}}}\n")
    truth: list[int] = []
    with open_router([free_endpoint]) as router:
        for watched in (False, True):
            sub = None
            if watched:
                def on_sample(sample: zenoh.Sample) -> None:
                    if sample.kind == zenoh.SampleKind.PUT:
                        truth.append(orjson.loads(sample.payload.to_bytes())["frame"])
                sub = router.declare_subscriber("mocapflow/truth/tracker/truth", on_sample)
            summary = tmp_path / f"watched-{watched}.json"
            done = run_cli("run", graph, "--connect", free_endpoint, "--summary", summary, timeout=120)
            assert done.returncode == 0, done.stdout + done.stderr
            time.sleep(0.3)
            if sub is not None:
                sub.undeclare()
            tracker = orjson.loads(summary.read_bytes())["tracker"]
            assert tracker["frames_out"] == (2 * frames if watched else frames), tracker
    assert truth == list(range(frames))
