"""deployments/c3d-replay.yaml over real Zenoh: a file replayed through the live pipeline gives the offline commands'
numbers, every frame of a real capture arrives, and unreadable files fail the run (and the offline commands) with a
one-line reason."""

from __future__ import annotations

import json
import subprocess
import warnings
from pathlib import Path

import c3d as c3d_package
import numpy as np
import pytest
import yaml
from conftest import CLI, free_port, run_cli

from mocapflow.io.markers import MarkerData, read_markers, write_markers
from mocapflow.mocap.model import Segment, SkeletonModel

pytestmark = pytest.mark.integration  # every test here starts processes and Zenoh sessions

ROOT = Path(__file__).resolve().parents[1]
DEPLOYMENT = ROOT / "deployments" / "c3d-replay.yaml"


def deployment(tmp_path: Path, endpoint: str, tag: str) -> tuple[Path, str]:
    """The shipped graph, unchanged but for a key prefix unique to this test and its own router endpoint."""
    graph = yaml.safe_load(DEPLOYMENT.read_text())
    graph["name"] = f"{tag}{endpoint.rsplit(':', 1)[1]}"
    graph["prefix"] = f"mocapflow/{graph['name']}"
    graph["zenoh"] = {"listen": [endpoint]}
    path = tmp_path / f"{tag}.yaml"
    path.write_text(yaml.safe_dump(graph, sort_keys=False))
    return path, graph["prefix"]


def start_replay(graph: Path, source: Path, output: Path, *settings: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [*CLI, "run", str(graph), "--duration", "120", "--set", f"tracker.path={source}", "--set",
         f"recorder.path={output}", *(arg for s in settings for arg in ("--set", s))],
        cwd=graph.parent, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def finish(run: subprocess.Popen[str]) -> str:
    out, _ = run.communicate(timeout=180)
    return out


def offline(*args: str | Path) -> None:
    done = run_cli(*args)
    assert done.returncode == 0, done.stderr



def assert_same_markers(live: MarkerData, reference: MarkerData) -> None:
    assert live.labels == reference.labels and live.rate == reference.rate
    assert live.first_frame == reference.first_frame
    np.testing.assert_array_equal(live.positions, reference.positions)
    np.testing.assert_array_equal(live.flags, reference.flags)


def real_slice(data_dir: Path, path: Path) -> MarkerData:
    """Six seconds of the lower-body capture with gaps cut into it: short ones, a long one, a whole cluster."""
    data = read_markers(data_dir / "lowerbody_clusters_knee_0401.c3d")
    rows = slice(1000, 1600)
    positions = data.positions[rows].copy()
    for label, start, stop in [("LTH2", 100, 160), ("RSH3", 200, 230), ("LASI", 300, 310), ("LSH1", 400, 420),
                               ("LSH2", 400, 420), ("LSH3", 400, 420), ("LSH4", 400, 420), ("RTOE", 450, 560)]:
        positions[start:stop, data.labels.index(label)] = np.nan
    cut = MarkerData(positions, data.labels, data.rate, data.first_frame + rows.start)
    write_markers(path, cut)
    return cut


def test_real_capture_through_the_pipeline_equals_fill_and_solve(tmp_path: Path, free_endpoint: str,
                                                                  data_dir: Path) -> None:
    source = tmp_path / "slice.c3d"
    real_slice(data_dir, source)
    offline("fill", source, "-o", tmp_path / "filled.c3d")
    offline("calibrate", tmp_path / "filled.c3d", "-o", tmp_path / "skeleton.json")
    offline("solve", tmp_path / "filled.c3d", "--skeleton", tmp_path / "skeleton.json", "-o", tmp_path / "solved.c3d")

    graph, _ = deployment(tmp_path, free_endpoint, "rs")
    out = finish(start_replay(graph, source, tmp_path / "live.c3d", f"skeleton.skeleton={tmp_path / 'skeleton.json'}",
                              "joints.refine=false", "tracker.speed=2"))
    assert "all nodes finished" in out, out

    live, filled = read_markers(tmp_path / "live.c3d"), read_markers(tmp_path / "filled.c3d")
    assert (filled.flags > 1).sum() > 250  # gaps were filled, by more than one case
    assert len(np.unique(filled.flags)) >= 3
    assert_same_markers(live, filled)

    solved = read_markers(tmp_path / "solved.c3d")
    skeleton = SkeletonModel.model_validate_json((tmp_path / "skeleton.json").read_text())
    assert list(live.extra) == list(solved.extra) == [j.name for j in skeleton.joints]
    for name, offline_track in solved.extra.items():
        track = live.extra[name]
        received = np.isfinite(track).all(1)
        count = int(received.sum())
        assert received.all(), (name, count)  # every frame posed, the last ones included
        assert np.isfinite(offline_track).all()
        np.testing.assert_allclose(track[received], offline_track[received], rtol=0, atol=1e-3)


def test_simulated_capture_through_the_pipeline_equals_fill(tmp_path: Path, free_endpoint: str) -> None:
    source = tmp_path / "sim.c3d"
    offline("simulate", "-o", source, "--frames", "720", "--set", "rate=120", "--set", "dropout_rate=1",
            "--set", "long_gaps=2", "--set", "seed=5")
    offline("fill", source, "-o", tmp_path / "filled.c3d")
    graph, _ = deployment(tmp_path, free_endpoint, "ss")
    # a short warm-up and joint window, so that segments and skeleton are learnt and solved within the six seconds
    out = finish(start_replay(graph, source, tmp_path / "live.c3d", "clusterer.warmup_s=2", "joints.window_s=3",
                              "joints.every_s=1"))
    assert "all nodes finished" in out, out
    live = read_markers(tmp_path / "live.c3d")
    assert_same_markers(live, read_markers(tmp_path / "filled.c3d"))
    # the skeleton learnt online was solved in the later frames: its joint centres lie near the simulated ones. Which
    # of its refits is in use when the capture ends depends on when the joint estimator's solves finish (on a busy
    # machine, later), and a refit may name its joints otherwise: the joints posed in the last frame are checked
    truth = np.load(tmp_path / "sim.truth.npz")
    final = {name: track for name, track in live.extra.items() if np.isfinite(track[-1]).all()}
    assert len(final) >= 0.75 * truth["joint_centres"].shape[1], (sorted(final), sorted(live.extra))
    for name, track in final.items():
        known = np.isfinite(track).all(1)
        error = np.linalg.norm(track[known, None] - truth["joint_centres"][known], axis=-1).mean(0)
        assert error.min() < 50.0, (name, error.min())  # a skeleton learnt from a 3 s window: coarse, not wrong


def test_cmu_capture_replays_every_frame(tmp_path: Path, free_endpoint: str, data_dir: Path) -> None:
    source = data_dir / "cmu_85_02.c3d"
    graph, _ = deployment(tmp_path, free_endpoint, "rc")
    summary = tmp_path / "summary.json"
    run = subprocess.Popen(
        [*CLI, "run", str(graph), "--set", f"tracker.path={source}", "--set", f"recorder.path={tmp_path / 'live.c3d'}",
         # windows short enough for a skeleton within the capture's 6.75 s: a run that never poses a frame fails
         "--set", "clusterer.warmup_s=2", "--set", "joints.window_s=3", "--set", "joints.every_s=1",
         "--summary", str(summary)], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out = finish(run)
    assert "all nodes finished" in out, out
    nodes = json.loads(summary.read_text())
    assert set(nodes) == {"tracker", "clusterer", "joints", "filler", "skeleton", "recorder"}
    assert all(n["state"] == "finished" and n["drops"] == 0 and n["errors"] == 0 for n in nodes.values()), nodes
    assert nodes["skeleton"]["frames_out"] > 0  # a skeleton was learnt and posed
    assert nodes["recorder"]["frames_in"] == 810 + nodes["skeleton"]["frames_out"]  # every frame and every pose
    data, live = read_markers(source), read_markers(tmp_path / "live.c3d")
    assert live.n_frames == data.n_frames == 810 and live.rate == data.rate == 120.0
    assert live.first_frame == data.first_frame and live.labels == data.labels
    seen = np.isfinite(data.positions).all(-1)
    np.testing.assert_array_equal(live.positions[seen], data.positions[seen])
    assert np.isfinite(live.positions).all(-1).all(1).all()


def unreadable_files(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    """A text file named .c3d, a C3D file cut in half, and a C3D file of analog channels only: path, reason."""
    text = tmp_path / "notes.c3d"
    text.write_text("not motion capture\n" * 100)
    whole = tmp_path / "whole.c3d"
    rng = np.random.default_rng(0)
    write_markers(whole, MarkerData(rng.uniform(-1e3, 1e3, (400, 10, 3)), [f"M{i}" for i in range(10)], 100.0))
    truncated = tmp_path / "half.c3d"
    truncated.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    analog_only = tmp_path / "emg.c3d"
    writer = c3d_package.Writer(point_rate=100.0, analog_rate=1000.0)
    writer.add_frames([(np.zeros((0, 5), np.float32), np.zeros((1, 10), np.float32))] * 50)
    with analog_only.open("wb") as handle, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the package warns that the file it writes has no points: that is the point
        writer.write(handle)
    return {"text": (text, "not a C3D file"), "truncated": (truncated, "truncated C3D file"),
            "no points": (analog_only, "holds no 3D points")}


def test_unreadable_file_fails_the_run_naming_it(tmp_path: Path, free_endpoint: str) -> None:
    files = unreadable_files(tmp_path)
    runs = {}
    for kind, endpoint in (("text", free_endpoint), ("truncated", f"tcp/127.0.0.1:{free_port()}")):
        graph, _ = deployment(tmp_path, endpoint, kind[:4])  # side by side: each waits for the drain timeout
        runs[kind] = start_replay(graph, files[kind][0], tmp_path / f"{kind}.c3d")
    for kind, run in runs.items():
        out = finish(run)
        path, reason = files[kind]
        assert run.returncode != 0, out
        assert "failed: tracker" in out
        assert any(str(path) in line and reason in line for line in out.splitlines()), out
        assert not (tmp_path / f"{kind}.c3d").exists()


@pytest.mark.parametrize("command", ["fill", "calibrate", "solve", "label"])
def test_offline_commands_refuse_unreadable_files_in_one_line(command: str, tmp_path: Path) -> None:
    skeleton = tmp_path / "skeleton.json"
    skeleton.write_text(SkeletonModel(segments=[Segment(name="a", markers=["M0"], marker_offsets=[(0, 0, 0)])],
                                      joints=[], root="a").model_dump_json())
    extra = ["--skeleton", skeleton] if command == "solve" else []
    for path, reason in unreadable_files(tmp_path).values():
        done = run_cli(command, path, "-o", tmp_path / "out.c3d", *extra)
        assert done.returncode == 2, (path, done.stderr)
        assert done.stderr.startswith(f"mocapflow {command}: error: {path}: "), done.stderr
        assert reason in done.stderr and done.stderr.count("\n") == 1, done.stderr
