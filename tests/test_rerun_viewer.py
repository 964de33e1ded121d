"""The Rerun viewer over real graph runs: the sink and ``mocapflow view`` save .rrd files that Rerun's own dataframe
API (a local catalog server over the file) reads back with the expected entities, frames, labels, colours by flag and
bones ending on the published joint centres."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from conftest import free_port
from test_replay_pipeline import real_slice

from mocapflow.io.markers import MarkerData, read_markers
from mocapflow.io.scene import FLAG_COLOURS, LOST, OTHER_ESTIMATE, SEGMENT_COLOURS, UNASSIGNED, up_axis_of_file
from mocapflow.runtime.graph import GraphError, load_graph

rr = pytest.importorskip("rerun")
pytest.importorskip("datafusion")

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "mocapflow.cli"]
ENV = {**os.environ, "RERUN_ANALYTICS": "0"}
SINK = {"markers": "filler/markers", "pose": "skeleton/pose", "skeleton": "joints/skeleton",
        "segments": "clusterer/segments"}


def read_rrd(path: Path, index: str | None = "frame") -> dict[str, list[Any]]:
    """An .rrd file as columns, one row per value of ``index`` (None: static data), through Rerun's catalog API."""
    folder = path.parent / f"{path.stem}.dataset"
    folder.mkdir()
    os.link(path, folder / path.name)
    server = rr.server.Server(datasets={"scene": str(folder)}, host="127.0.0.1")
    try:
        client = server.client()  # the client must outlive the query
        table = client.get_dataset("scene").reader(index=index).to_arrow_table()
    finally:
        server.shutdown()
    return table.to_pydict()


def rows(table: dict[str, list[Any]], entity: str, component: str) -> dict[int, Any]:
    """frame -> value of one entity's component, where it was logged."""
    column = table[f"/{entity}:{component}"]
    return {f: v for f, v in zip(table["frame"], column, strict=True) if v is not None}


def rgb(packed: int) -> tuple[int, int, int]:
    return packed >> 24 & 255, packed >> 16 & 255, packed >> 8 & 255


def graph_with_sinks(tmp_path: Path, base: str, endpoint: str, sinks: dict[str, dict[str, Any]],
                     tracker: dict[str, Any], short_windows: bool) -> Path:
    graph = yaml.safe_load((ROOT / "deployments" / base).read_text())
    graph["name"] = f"rr{endpoint.rsplit(':', 1)[1]}"
    graph["prefix"] = f"mocapflow/{graph['name']}"
    graph["zenoh"] = {"listen": [endpoint]}
    graph["nodes"]["tracker"]["config"].update(tracker)
    graph["nodes"]["recorder"]["config"]["path"] = str(tmp_path / "recorded.c3d")
    if short_windows:  # segments and skeleton learnt within seconds
        graph["nodes"]["clusterer"]["config"] = {"window_s": 2}
        graph["nodes"]["joints"]["config"] = {"window_s": 3, "every_s": 1}
    graph["nodes"].update(sinks)
    path = tmp_path / "graph.yaml"
    path.write_text(yaml.safe_dump(graph, sort_keys=False))
    return path


def run(*args: str | Path, timeout: float = 240) -> str:
    done = subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=timeout, env=ENV)
    assert done.returncode == 0, done.stdout + done.stderr
    return done.stdout + done.stderr


def column(recorded: MarkerData, label: str) -> int:
    """A marker's column in the recorded file. The labeller names its track t ``M{t+1:03d}``, and the recorder keeps
    the stream's row order but names its columns ``P{t+1:03d}`` when tracks were added during the run."""
    return recorded.labels.index(label) if label in recorded.labels else int(label[1:]) - 1


def check_markers(table: dict[str, list[Any]], entity: str, recorded: MarkerData) -> tuple[set[int], set[int]]:
    """Every drawn marker has its label, its recorded position and flag, and the colour of its flag (observed: of
    its segment; lost: grey, where last seen). Returns the frames drawn and the flags seen."""
    positions = rows(table, entity, "Points3D:positions")
    labels, colours = rows(table, entity, "Points3D:labels"), rows(table, entity, "Points3D:colors")
    classes = rows(table, entity, "Points3D:class_ids")
    assert positions and set(positions) == set(labels) == set(colours) == set(classes)
    seen: set[int] = set()
    segment_colours = {tuple(c) for c in SEGMENT_COLOURS} | {UNASSIGNED}
    for frame, xyz in positions.items():
        row = frame - recorded.first_frame
        index = [column(recorded, label) for label in labels[frame]]
        flags = recorded.flags[row, index]
        drawn = np.asarray(classes[frame])
        present = drawn != 0
        np.testing.assert_array_equal(drawn[present], flags[present])
        assert (flags[~present] == 0).all()
        np.testing.assert_allclose(np.reshape(xyz, (-1, 3))[present], recorded.positions[row, index][present], atol=1e-3)
        for flag, colour in zip(drawn, colours[frame], strict=True):
            expected = {0: {LOST}, 1: segment_colours}.get(int(flag), {FLAG_COLOURS.get(flag, OTHER_ESTIMATE)})
            assert rgb(colour) in expected, (frame, flag, rgb(colour))
        seen.update(int(f) for f in drawn)
    return set(positions), seen


def check_bones(table: dict[str, list[Any]], entity: str, recorded: MarkerData) -> int:
    """Each bone is a two-point strip between the published centres of the joints it names; returns frames seen."""
    strips, labels = rows(table, f"{entity}/bones", "LineStrips3D:strips"), rows(table, f"{entity}/bones",
                                                                                 "LineStrips3D:labels")
    joints = rows(table, f"{entity}/joints", "Points3D:positions")
    assert strips and set(strips) <= set(joints)
    for frame, frame_strips in strips.items():
        row = frame - recorded.first_frame
        assert len(frame_strips) == len(labels[frame]) > 0
        for strip, label in zip(frame_strips, labels[frame], strict=True):
            a, b = label.split(" → ")
            np.testing.assert_allclose(strip, [recorded.extra[a][row], recorded.extra[b][row]], atol=1e-3)
    return len(strips)


@pytest.mark.integration
def test_sink_draws_a_simulated_capture_with_rays(tmp_path: Path, free_endpoint: str) -> None:
    sinks = {
        "viewer": {"plugin": "rerun", "inputs": SINK, "config": {"save": str(tmp_path / "scene.rrd"), "rate": None}},
        "rays": {"plugin": "rerun", "inputs": {"markers": "labeller/markers"},
                 "config": {"save": str(tmp_path / "rays.rrd"), "ray_length_mm": 3000}},
    }
    graph = graph_with_sinks(tmp_path, "cameras.yaml", free_endpoint, sinks, {"frames": 1200, "rate": 120}, True)
    out = run("run", graph, "--duration", "150")
    assert "all nodes finished" in out, out
    recorded = read_markers(tmp_path / "recorded.c3d")

    table = read_rrd(tmp_path / "scene.rrd")
    assert {"/world/markers:Points3D:positions", "/world/pose/joints:Points3D:positions",
            "/world/pose/bones:LineStrips3D:strips"} <= set(table)
    frames, flags = check_markers(table, "world/markers", recorded)
    assert frames == set(range(recorded.first_frame, recorded.first_frame + recorded.n_frames))  # rate null: all
    assert recorded.n_frames == 1200
    assert {1, 7} <= flags and len(flags - {0, 1}) >= 3, flags  # observed, rays and other fill cases
    assert check_bones(table, "world/pose", recorded) > 100

    rays = read_rrd(tmp_path / "rays.rrd")
    strips = rows(rays, "world/markers/rays", "LineStrips3D:strips")
    drawn = rows(rays, "world/markers", "Points3D:positions")
    assert strips and set(strips) <= set(drawn)
    assert 0 < len(drawn) < 1200 and max(drawn) == 1199  # 60 Hz display of a 120 Hz stream; the last frame shown
    segments = np.array([s for f in strips.values() for s in f])
    # a labelled marker seen by one camera has no position: its ray is drawn ray_length_mm from that camera
    np.testing.assert_allclose(np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1), 3000, atol=0.01)
    assert len(np.unique(segments[:, 0].round(1), axis=0)) <= 8  # every ray starts at one of the 8 cameras
    colours = {rgb(c) for row in rays["/world/markers/rays:LineStrips3D:colors"] if row for c in row}
    assert colours == {FLAG_COLOURS[7]}
