"""The qtm and natnet tracker plugins in graphs run by ``mocapflow run`` (real processes, real Zenoh on loopback)
against the stand-in servers: every frame of a real file reaches the recorder in order with the file's values, the
filler's output equals the c3d-replay graph's, a server restarted mid-stream is reconnected with frame numbers still
increasing and the gap counted as drops, and a server absent at start fails the run in one line."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import CLI, free_port
from scipy.optimize import linear_sum_assignment
from test_runtime import wait_for_frames
from trackers import Server, graph_file, run_graph, stream_graph

from mocapflow.io.markers import MarkerData, read_markers, write_markers

pytestmark = pytest.mark.integration
pytest.importorskip("qtm_rt")
pytest.importorskip("natnet")

SHORT = "cmu_dribble_shoot_basketball.c3d"


def tracker(protocol: str, port: int, unlabelled: bool = False) -> dict:
    if protocol == "qtm":
        config = {"port": port, "end_with_capture": True, "component": "3dnolabels" if unlabelled else "3d"}
    else:
        config = {"command_port": port, "multicast": False, "end_after_s": 5.0,
                  "markers": "unlabelled" if unlabelled else "labelled"}
    return {"plugin": protocol, "config": config}


def recorder(output: Path, source: str = "tracker/markers") -> dict:
    return {"plugin": "recorder", "inputs": {"markers": source}, "config": {"path": str(output)}}


@pytest.mark.parametrize("protocol", ["qtm", "natnet"])
def test_every_frame_reaches_the_recorder(protocol: str, tmp_path: Path, free_endpoint: str, real_file) -> None:
    """Labelled markers, every frame with the file's values (the unlabelled point cloud: the labeller's test below)."""
    path = real_file(SHORT)
    data = read_markers(path)
    port = free_port()
    graph = graph_file(tmp_path, free_endpoint, f"{protocol[0]}0",
                       {"tracker": tracker(protocol, port), "recorder": recorder(tmp_path / "live.c3d")})
    code, out, stats = stream_graph(protocol, path, port, graph, "recorder", "--speed", "2")
    assert code == 0 and "all nodes finished" in out, out
    assert stats["recorder"]["frames_in"] == len(data.positions), stats
    assert stats["recorder"]["drops"] == 0 and stats["recorder"]["errors"] == 0, stats  # in order, none missing
    live = read_markers(tmp_path / "live.c3d")
    assert live.first_frame == data.first_frame and live.rate == data.rate
    assert live.labels == data.labels and len(live.positions) == len(data.positions)
    # both protocols carry float32: QTM the file's mm exactly as float32, NatNet metres (a rounding of ~1e-4 mm)
    tolerance = 1e-3 if protocol == "natnet" else 0
    np.testing.assert_allclose(live.positions, data.positions.astype(np.float32), rtol=0, atol=tolerance)


def gappy_slice(data_dir: Path, path: Path) -> None:
    """Five seconds of the lower-body capture with gaps cut into it, short and long, written to ``path``."""
    data = read_markers(data_dir / "lowerbody_clusters_knee_0401.c3d")
    positions = data.positions[1000:1500].copy()
    for label, start, stop in [("LTH2", 100, 160), ("RSH3", 200, 230), ("LSH1", 300, 320), ("RTOE", 350, 450)]:
        positions[start:stop, data.labels.index(label)] = np.nan
    write_markers(path, MarkerData(positions, data.labels, data.rate, data.first_frame + 1000))


def filling(output: Path) -> dict:
    return {"filler": {"plugin": "occlusion-filler", "inputs": {"markers": "tracker/markers"}},
            "recorder": recorder(output, "filler/markers")}


@pytest.fixture(scope="module")
def filled_by_replay(tmp_path_factory: pytest.TempPathFactory, data_dir: Path) -> tuple[Path, Path]:
    """The gappy slice, and the filler's output of it in the c3d-replay graph (once for both protocols)."""
    tmp = tmp_path_factory.mktemp("filled")
    source = tmp / "slice.c3d"
    gappy_slice(data_dir, source)
    replay = graph_file(tmp, f"tcp/127.0.0.1:{free_port()}", "fr", {
        "tracker": {"plugin": "c3d-replay", "config": {"path": str(source), "speed": 2}},
        **filling(tmp / "replay.c3d")})
    code, out, _ = run_graph(replay)
    assert code == 0, out
    return source, tmp / "replay.c3d"


@pytest.mark.xdist_group("filled_by_replay")
@pytest.mark.parametrize("protocol", ["qtm", "natnet"])
def test_filled_output_equals_the_c3d_replay_graph(protocol: str, tmp_path: Path, free_endpoint: str,
                                                   filled_by_replay: tuple[Path, Path]) -> None:
    source, replayed = filled_by_replay
    port = free_port()
    live = graph_file(tmp_path, free_endpoint, f"fl{protocol[0]}",
                      {"tracker": tracker(protocol, port), **filling(tmp_path / "live.c3d")})
    code, out, _ = stream_graph(protocol, source, port, live, "filler", "--speed", "2")
    assert code == 0, out
    got, expected = read_markers(tmp_path / "live.c3d"), read_markers(replayed)
    assert got.labels == expected.labels and got.first_frame == expected.first_frame
    assert (expected.flags > 1).sum() > 100  # the filler filled the gaps
    np.testing.assert_array_equal(got.flags, expected.flags)
    # the trackers carry float32 (QTM mm, NatNet metres): inputs differ from the file's by up to ~1e-4 mm
    np.testing.assert_allclose(got.positions, expected.positions, rtol=0, atol=0.01)


@pytest.mark.parametrize("protocol", ["qtm", "natnet"])
def test_server_restarted_mid_stream_is_reconnected(protocol: str, tmp_path: Path, free_endpoint: str,
                                                     real_file) -> None:
    path = real_file(SHORT)
    data = read_markers(path)
    port = free_port()
    node = tracker(protocol, port)
    node["config"]["end_after_s"] = 15.0 if protocol == "natnet" else None  # longer than a restart on a busy machine
    node["config"] = {k: v for k, v in node["config"].items() if v is not None}
    graph = graph_file(tmp_path, free_endpoint, f"rs{protocol[0]}", {"tracker": node,
                                                                      "recorder": recorder(tmp_path / "live.c3d")})
    server = Server(protocol, path, port, "--loop")
    run = subprocess.Popen([*CLI, "run", str(graph), "--duration", "150", "--summary", str(tmp_path / "s.json")],
                           cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        wait_for_frames(free_endpoint, f"mocapflow/rs{protocol[0]}{free_endpoint.rsplit(':', 1)[1]}", "recorder",
                        len(data.positions) // 2)  # the graph starts, and part of the file streams
        server.stop()
        time.sleep(2)
        server = Server(protocol, path, port)  # plays the file again from its first frame, once
        out, _ = run.communicate(timeout=150)
    finally:
        server.stop()
        if run.poll() is None:
            run.terminate()
            run.wait(timeout=30)
    import json

    assert run.returncode == 0, out
    stats = json.loads((tmp_path / "s.json").read_text())["recorder"]
    live = read_markers(tmp_path / "live.c3d")
    received = np.isfinite(live.positions).any(axis=(1, 2))
    assert stats["frames_in"] == received.sum() > len(data.positions), out  # part of the file, then all of it
    assert stats["drops"] > 100, stats  # the frames of the silence (two seconds and more at 120 Hz)
    assert stats["errors"] == 0, stats  # never a frame number at or below the one before
    assert received.sum() + stats["drops"] == len(live.positions)
    tail = live.positions[-len(data.positions):]  # the replayed file, whole, at the end
    arrived = np.isfinite(tail).any(axis=(1, 2))
    # QTM streams over TCP: every frame; NatNet over UDP, which a busy machine may drop a datagram of
    assert arrived.all() if protocol == "qtm" else arrived.mean() > 0.99, np.flatnonzero(~arrived)
    tolerance = 1e-3 if protocol == "natnet" else 0
    np.testing.assert_allclose(tail[arrived], data.positions[arrived].astype(np.float32), rtol=0, atol=tolerance)


@pytest.mark.parametrize("protocol", ["qtm", "natnet"])
def test_absent_server_fails_the_run_in_one_line(protocol: str, tmp_path: Path, free_endpoint: str) -> None:
    port = free_port()
    graph = graph_file(tmp_path, free_endpoint, f"ab{protocol[0]}",
                       {"tracker": tracker(protocol, port), "recorder": recorder(tmp_path / "live.c3d")})
    code, out, stats = run_graph(graph, "tracker.timeout_s=1")
    # the node exits with code 2 (a configuration error, not restarted), after one line naming the server; so does
    # the run
    assert code == 2, out
    assert "[tracker] failed for good (configuration error)" in out, out
    reasons = {line.split("could not start: ", 1)[1] for line in out.splitlines() if "could not start: " in line}
    assert len(reasons) == 1 and f"127.0.0.1:{port}" in reasons.pop(), out
    assert "Traceback" not in out and "Errno" not in out, out
    assert stats["tracker"]["state"] == "failed" and stats["tracker"]["restarts"] == 0, stats


def labelling(output: Path) -> dict:
    return {"labeller": {"plugin": "labeller", "inputs": {"markers": "tracker/markers"}},
            "recorder": recorder(output, "labeller/markers")}


@pytest.fixture(scope="module")
def labelled_by_replay(tmp_path_factory: pytest.TempPathFactory, real_file) -> Path:
    """The labeller's output of the short capture's point cloud in the c3d-replay graph (once for both protocols)."""
    path = real_file(SHORT)
    tmp = tmp_path_factory.mktemp("labelled")
    replay = graph_file(tmp, f"tcp/127.0.0.1:{free_port()}", "lr", {
        "tracker": {"plugin": "c3d-replay", "config": {"path": str(path), "speed": 2, "unlabelled": True}},
        **labelling(tmp / "replay.c3d")})
    code, out, _ = run_graph(replay)
    assert code == 0, out
    return tmp / "replay.c3d"


@pytest.mark.xdist_group("labelled_by_replay")
@pytest.mark.parametrize("protocol", ["qtm", "natnet"])
def test_labelled_point_cloud_equals_the_c3d_replay_graph(protocol: str, tmp_path: Path, free_endpoint: str,
                                                          real_file, labelled_by_replay: Path) -> None:
    """Unlabelled points from the tracker, every frame, labelled by the labeller: the same tracks as from
    c3d-replay's point cloud of the same file (the point order differs, so tracks are matched by their
    trajectories), each point within float32's rounding of the file's."""
    path = real_file(SHORT)
    port = free_port()
    live = graph_file(tmp_path, free_endpoint, f"lb{protocol[0]}",
                      {"tracker": tracker(protocol, port, unlabelled=True), **labelling(tmp_path / "live.c3d")})
    code, out, stats = stream_graph(protocol, path, port, live, "labeller", "--speed", "2")
    assert code == 0, out
    assert stats["labeller"]["frames_in"] == read_markers(path).n_frames, stats
    assert stats["labeller"]["drops"] == 0 and stats["labeller"]["errors"] == 0, stats  # in order, none missing
    got, expected = read_markers(tmp_path / "live.c3d"), read_markers(labelled_by_replay)
    assert got.first_frame == expected.first_frame and len(got.positions) == len(expected.positions)
    assert len(got.labels) == len(expected.labels) >= 41
    a, b = got.positions.transpose(1, 0, 2), expected.positions.transpose(1, 0, 2)  # tracks x frames x 3
    both = np.isfinite(a[:, None, :, 0]) & np.isfinite(b[None, :, :, 0])
    gap = np.where(both, np.linalg.norm(a[:, None] - b[None], axis=3), 0).sum(axis=2)
    gap += (np.isfinite(a[:, None, :, 0]) != np.isfinite(b[None, :, :, 0])).sum(axis=2) * 1e6
    rows, cols = linear_sum_assignment(gap)
    for row, col in zip(rows, cols, strict=True):
        np.testing.assert_array_equal(np.isfinite(a[row]), np.isfinite(b[col]))  # same frames in each track
        seen = np.isfinite(a[row][:, 0])
        np.testing.assert_allclose(a[row][seen], b[col][seen], rtol=0, atol=0.01)
