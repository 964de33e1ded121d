"""Single-camera rays through the live pipeline over real Zenoh: the simulated tracker's camera model publishes them,
the occlusion filler puts those markers on their rays, and the recording equals the same filling done offline."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import run_cli

from mocapflow.io.markers import MarkerData, read_markers
from mocapflow.io.skeleton import write_skeleton
from mocapflow.mocap.filling import FillCase, FillerConfig, GapFiller
from mocapflow.mocap.rigs import make_rig
from mocapflow.mocap.simulator import SimulatorConfig, simulate, truth_skeleton

pytestmark = pytest.mark.integration  # every test here starts processes and Zenoh sessions

FRAMES = 360


def run_graph(tmp_path: Path, endpoint: str, nodes: dict[str, dict]) -> MarkerData:
    """Run a graph of ``nodes`` plus a recorder of ``filler/markers`` to the end, over its own router; the recording."""
    name = f"rays{endpoint.rsplit(':', 1)[1]}"
    recorder = {"plugin": "recorder", "inputs": {"markers": "filler/markers"},
                "config": {"path": str(tmp_path / "live.c3d")}}
    graph = {"name": name, "prefix": f"mocapflow/{name}", "zenoh": {"listen": [endpoint]},
             "nodes": {**nodes, "recorder": recorder}}
    (tmp_path / "graph.yaml").write_text(yaml.safe_dump(graph, sort_keys=False))
    run = run_cli("run", tmp_path / "graph.yaml", "--duration", "60")
    assert run.returncode == 0 and "all nodes finished" in run.stdout + run.stderr, run.stdout + run.stderr
    return read_markers(tmp_path / "live.c3d")


def test_rays_from_the_simulated_cameras_reach_the_filler(tmp_path: Path, free_endpoint: str) -> None:
    tracker = {"rate": 120, "seed": 7, "noise_mm": 0.5, "skin_mm": 1.0, "cameras": 3}
    rec = simulate(SimulatorConfig(**tracker), FRAMES)
    assert rec.rays is not None
    ray = np.isfinite(rec.rays).all(-1)
    assert ray.mean() > 0.05
    skeleton = truth_skeleton(make_rig("human"), rec.true_positions[0])
    write_skeleton(tmp_path / "skeleton.json", skeleton)
    live = run_graph(tmp_path, free_endpoint, {
        "tracker": {"plugin": "simulator", "config": {**tracker, "frames": FRAMES}},
        "filler": {"plugin": "occlusion-filler", "inputs": {"markers": "tracker/markers"},
                   "config": {"skeleton": str(tmp_path / "skeleton.json")}},
    })
    assert live.positions.shape == rec.positions.shape and live.flags is not None

    # the same filling offline, from the frames as they travel (float32 on the wire)
    filler = GapFiller(rec.labels, rec.rate, FillerConfig(), skeleton)
    wire = rec.positions.astype(np.float32).astype(np.float64)
    rays = rec.rays.astype(np.float32).astype(np.float64)
    offline = np.array([filler.update(wire[f], rays[f]).positions for f in range(FRAMES)])
    np.testing.assert_array_equal(live.flags == FillCase.RAY, ray)
    np.testing.assert_allclose(live.positions, offline, rtol=0, atol=1e-2)  # C3D stores float32
    error = np.linalg.norm(live.positions[ray] - rec.true_positions[ray], axis=-1).mean()
    assert error < 2.5, error


def test_simulate_command_keeps_the_rays_beside_the_file(tmp_path: Path) -> None:
    out = tmp_path / "cams.c3d"
    done = run_cli("simulate", "-o", out, "--frames", "60", "--set", "cameras=3", "--set", "rate=120")
    assert done.returncode == 0, done.stderr
    rays = np.load(out.with_suffix(".truth.npz"))["rays"]
    expected = simulate(SimulatorConfig(cameras=3, rate=120), 60)
    assert expected.rays is not None
    np.testing.assert_array_equal(rays, expected.rays)
    positions = read_markers(out).positions
    assert np.isnan(positions[np.isfinite(rays).all(-1)]).all()  # a ray's marker is not a point in the file
    assert np.isfinite(rays).all(-1).any()


def test_fill_command_takes_the_rays(tmp_path: Path) -> None:
    """`mocapflow fill --rays` puts the single-camera markers of a simulated file on their rays, closer to the truth
    than filling without them; a rays file that does not fit the recording is refused in one line."""
    source = tmp_path / "cams.c3d"
    made = run_cli("simulate", "-o", source, "--frames", "1200", "--set", "cameras=3", "--set", "rate=120")
    assert made.returncode == 0
    truth = np.load(source.with_suffix(".truth.npz"))
    ray = np.isfinite(truth["rays"]).all(-1)
    errors = []
    for extra in (["--rays", source.with_suffix(".truth.npz")], []):
        done = run_cli("fill", source, "-o", tmp_path / "filled.c3d", *extra)
        assert done.returncode == 0, done.stderr
        filled = read_markers(tmp_path / "filled.c3d")
        assert filled.flags is not None
        on_ray = filled.flags == FillCase.RAY
        if extra:
            assert not (on_ray & ~ray).any() and on_ray[ray].mean() > 0.95
        else:
            assert not on_ray.any()
        errors.append(np.nanmean(np.linalg.norm(filled.positions[ray] - truth["true_positions"][ray], axis=-1)))
    assert errors[0] < 0.5 * errors[1], errors
    np.savez(tmp_path / "short.npz", rays=truth["rays"][:10])
    for bad, reason in ((tmp_path / "short.npz", "rays are 10 x 52 x 6"), (source, "not an .npz file")):
        done = run_cli("fill", source, "-o", tmp_path / "x.c3d", "--rays", bad)
        assert done.returncode == 2 and reason in done.stderr and len(done.stderr.strip().splitlines()) == 1, (
            done.stderr)


def test_rays_of_an_unlabelled_cloud_reach_the_filler_through_the_labeller(tmp_path: Path, free_endpoint: str) -> None:
    """Unlabelled points and rays -> labeller (with the filler's predictions) -> filler learning the body: the
    labeller attributes the rays to the markers it did not see, and the filler puts those markers on them, mostly
    next to where they truly are."""
    frames = 1200
    tracker = {"rate": 120, "seed": 3, "noise_mm": 0.5, "cameras": 4, "unlabelled": True, "ghosts": 0.5}
    rec = simulate(SimulatorConfig(**tracker), frames)
    live = run_graph(tmp_path, free_endpoint, {
        "tracker": {"plugin": "simulator", "config": {**tracker, "frames": frames}},
        "labeller": {"plugin": "labeller", "inputs": {"markers": "tracker/markers",
                                                      "predictions": "filler/predictions"}},
        "filler": {"plugin": "occlusion-filler", "inputs": {"markers": "labeller/markers"}},
    })
    assert live.flags is not None and len(live.positions) == frames
    on_ray = np.argwhere(live.flags == FillCase.RAY)
    assert len(on_ray) > 100
    placed = live.positions[on_ray[:, 0], on_ray[:, 1]]
    nearest = np.linalg.norm(rec.true_positions[on_ray[:, 0]] - placed[:, None], axis=-1).min(axis=1)
    # most sit within noise of a true marker; the tail is markers of segments not learnt yet, whose depth along the
    # ray only their own filter gives
    assert np.median(nearest) < 2.5 and np.mean(nearest < 25.0) > 0.85, np.percentile(nearest, [50, 90, 99])
