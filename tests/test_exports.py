"""Exports for downstream tools, each read back by an independent reader: BVH by bvhio (and by ours), C3D by ezc3d and
by the ``c3d`` package, TRC by a plain text parse. Joint positions are checked against the solver's joint centres."""

from __future__ import annotations

import warnings
from pathlib import Path

import bvhio
import c3d as c3d_package
import ezc3d
import numpy as np
import pytest
from conftest import run_cli

from mocapflow.io.bvh import Bvh, read_bvh, skeleton_bvh, write_bvh
from mocapflow.io.markers import FLAG_ESTIMATED, FLAG_OBSERVED, read_markers
from mocapflow.mocap.model import SkeletonModel
from mocapflow.mocap.rigs import make_rig
from mocapflow.mocap.simulator import SimRecording, SimulatorConfig, simulate, truth_skeleton
from mocapflow.mocap.solve import SkeletonPose, solve

RATE = 120.0


def solved_human(frames: int, **config: object) -> tuple[SimRecording, SkeletonModel, SkeletonPose]:
    """A simulated human solved with its true skeleton."""
    rec = simulate(SimulatorConfig(rig="human", rate=RATE, seed=1, **config), frames)
    skeleton = truth_skeleton(make_rig("human"), rec.true_positions[0])
    return rec, skeleton, solve(skeleton, rec.positions, rec.labels)


def bvhio_positions(path: Path) -> tuple[list[str], list[str | None], np.ndarray]:
    """Joint names, parent names and world positions (F, J, 3) of every frame, as bvhio computes them."""
    root = bvhio.readAsHierarchy(str(path))
    joints = [joint for joint, _, _ in root.layout()]
    frames = bvhio.readAsBvh(str(path)).FrameCount
    positions = np.empty((frames, len(joints), 3))
    for f in range(frames):
        root.loadPose(f)
        positions[f] = [tuple(joint.PositionWorld) for joint in joints]
    return [j.Name for j in joints], [j.Parent.Name if j.Parent else None for j in joints], positions


def expected_tree(skeleton: SkeletonModel) -> dict[str, str | None]:
    """BVH joint name -> parent BVH joint name: the root segment, then one joint per skeleton joint, under the joint
    that moves with its parent segment."""
    node_of_segment = {skeleton.root: skeleton.root} | {j.child: j.name for j in skeleton.joints}
    return {skeleton.root: None} | {j.name: node_of_segment[j.parent] for j in skeleton.joints}


def joint_columns(bvh: Bvh, pose: SkeletonPose) -> tuple[list[int], list[int]]:
    """BVH joint indices and the matching columns of ``pose.joint_centres``."""
    pairs = [(k, pose.joint_names.index(name)) for k, name in enumerate(bvh.names) if name in pose.joint_names]
    return [k for k, _ in pairs], [j for _, j in pairs]


@pytest.mark.parametrize("order", ["ZXY", "XYZ"])
def test_bvh_of_a_simulated_human_reads_back_in_bvhio_and_ours(order: str, tmp_path: Path) -> None:
    rec, skeleton, pose = solved_human(240)
    path = tmp_path / "human.bvh"
    write_bvh(path, skeleton_bvh(skeleton, pose, RATE, order))

    ours = read_bvh(path)
    tree = expected_tree(skeleton)
    assert sorted(ours.names) == sorted(tree) and ours.names[0] == skeleton.root
    assert {n: (ours.names[p] if p >= 0 else None) for n, p in zip(ours.names, ours.parents, strict=True)} == tree
    assert ours.frames == 240 and ours.rate == pytest.approx(RATE, rel=1e-6)
    assert ours.channels[0] == ("Xposition", "Yposition", "Zposition", *(f"{a}rotation" for a in order))
    assert all(c == tuple(f"{a}rotation" for a in order) for c in ours.channels[1:])

    names, parents, positions = bvhio_positions(path)
    assert names == ours.names and len(positions) == 240
    assert dict(zip(names, parents, strict=True)) == tree

    columns, centres = joint_columns(ours, pose)
    assert len(columns) == len(skeleton.joints) == 14
    truth = rec.joint_centres[:, [rec.joint_names.index(pose.joint_names[j]) for j in centres]]
    for fk in (ours.forward_kinematics(), positions):
        error = np.linalg.norm(fk[:, columns] - pose.joint_centres[:, centres], axis=-1)
        assert error.max() < 1.0, error.max()
        # and the solver's centres are the simulated ones, so the file is the subject's motion, not just consistent
        assert np.linalg.norm(fk[:, columns] - truth, axis=-1).mean() < 3.0
    np.testing.assert_allclose(ours.root_translation, pose.translations[:, 0], atol=1e-5)


def test_bvh_end_sites_sit_at_the_marker_centroid_of_end_segments(tmp_path: Path) -> None:
    _, skeleton, pose = solved_human(60)
    path = tmp_path / "human.bvh"
    write_bvh(path, skeleton_bvh(skeleton, pose, RATE))
    bvh = read_bvh(path)
    rotations, positions = bvh.world_transforms()
    child_of = {j.name: j.child for j in skeleton.joints}
    ends = {k: child_of[bvh.names[k]] for k in bvh.end_sites}
    assert sorted(ends.values()) == ["head", "left_foot", "left_hand", "right_foot", "right_hand"]
    for k, segment in ends.items():
        tip = np.einsum("fab,b->fa", rotations[:, k], bvh.end_sites[k]) + positions[:, k]
        np.testing.assert_allclose(tip, pose.translations[:, pose.segment_names.index(segment)], atol=1e-3)


def test_bvh_holds_the_last_pose_of_a_segment_the_solver_lost(tmp_path: Path) -> None:
    rec = simulate(SimulatorConfig(rig="human", rate=RATE, seed=1), 240)
    skeleton = truth_skeleton(make_rig("human"), rec.true_positions[0])
    hidden = [m for s in skeleton.segments if s.name in ("left_forearm", "left_hand") for m in s.markers]
    positions = rec.positions.copy()
    positions[100:200, [rec.labels.index(m) for m in hidden]] = np.nan
    pose = solve(skeleton, positions, rec.labels)
    lost = ~np.isfinite(pose.rotations[:, pose.segment_names.index("left_forearm")]).all(-1)
    np.testing.assert_array_equal(np.flatnonzero(lost), np.arange(100, 200))
    path = tmp_path / "human.bvh"
    write_bvh(path, skeleton_bvh(skeleton, pose, RATE))
    bvh = read_bvh(path)
    assert np.isfinite(bvh.rotations).all()
    elbow, wrist = bvh.names.index("left_elbow"), bvh.names.index("left_wrist")
    np.testing.assert_allclose(bvh.rotations[100:200, elbow], bvh.rotations[[99] * 100, elbow], atol=1e-6)
    assert not np.allclose(bvh.rotations[200, elbow], bvh.rotations[99, elbow], atol=1e-3)
    columns, centres = joint_columns(bvh, pose)
    fk = bvh.forward_kinematics()
    known = np.isfinite(pose.joint_centres[:, centres]).all(-1)
    assert not known.all()  # the wrist is unknown to the solver while both its segments are hidden...
    error = np.linalg.norm(fk[:, columns] - pose.joint_centres[:, centres], axis=-1)[known]
    assert error.max() < 1.0, error.max()
    # ...and placed by the held forearm in the BVH, so an animation tool never sees a missing joint
    assert np.isfinite(fk[:, wrist]).all()


def test_bvh_writer_rejects_what_a_bvh_file_cannot_hold(tmp_path: Path) -> None:
    _, skeleton, pose = solved_human(10)
    bvh = skeleton_bvh(skeleton, pose, RATE)
    bvh.rotations[3, 2] = np.nan
    with pytest.raises(ValueError, match="finite"):
        write_bvh(tmp_path / "x.bvh", bvh)
    with pytest.raises(ValueError, match="permutation of XYZ"):
        skeleton_bvh(skeleton, pose, RATE, "XXY")


# Files written by the offline commands ---------------------------------------------------------------------------


def cli(*args: str | Path) -> str:
    done = run_cli(*args)
    assert done.returncode == 0, done.stderr
    return done.stdout


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """simulate -> fill -> calibrate -> solve, writing every export format."""
    out = tmp_path_factory.mktemp("exports")
    cli("simulate", "-o", out / "sim.c3d", "--frames", "1200", "--set", "rate=120", "--set", "dropout_rate=0.5",
        "--set", "seed=2")
    cli("fill", out / "sim.c3d", "-o", out / "filled.c3d")
    cli("calibrate", out / "filled.c3d", "-o", out / "skeleton.json")
    for suffix in ("c3d", "trc", "bvh"):
        cli("solve", out / "filled.c3d", "--skeleton", out / "skeleton.json", "-o", out / f"solved.{suffix}")
    return out


def read_with_c3d_package(path: Path) -> tuple[np.ndarray, list[str]]:
    """Points (F, N, 5: x, y, z, residual, camera byte) and labels as the ``c3d`` package reads them."""
    with path.open("rb") as handle, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no analog data found"
        reader = c3d_package.Reader(handle)
        points = np.stack([frame for _, frame, _ in reader.read_frames()])
        labels = [str(label).strip() for label in reader.get("POINT:LABELS").string_array]
    return points, labels


@pytest.mark.integration
@pytest.mark.xdist_group("exported")  # one worker makes the exports for all three
def test_filled_c3d_flags_read_the_same_in_ezc3d_and_the_c3d_package(exported: Path) -> None:
    sim = read_markers(exported / "sim.c3d")
    filled = read_markers(exported / "filled.c3d")
    observed = np.isfinite(sim.positions).all(-1)
    assert (~observed).sum() > 500  # the dropouts left gaps to fill
    assert (filled.flags[observed] == FLAG_OBSERVED).all()
    assert (filled.flags[~observed] >= FLAG_ESTIMATED).all() and len(np.unique(filled.flags[~observed])) > 1

    c3d = ezc3d.c3d(str(exported / "filled.c3d"))
    assert c3d["parameters"]["POINT"]["LABELS"]["value"] == sim.labels
    residuals = c3d["data"]["meta_points"]["residuals"][0].T
    assert (residuals[observed] > 0).all() and (residuals[~observed] == 0).all()
    assert "FLAG_RUNS" in c3d["parameters"]["MOCAPFLOW"]

    points, labels = read_with_c3d_package(exported / "filled.c3d")
    assert labels == sim.labels
    assert (points[..., 3][observed] > 0).all() and (points[..., 3][~observed] == 0).all()
    np.testing.assert_array_equal(points[..., :3], filled.positions)
    np.testing.assert_array_equal(c3d["data"]["points"][:3].transpose(2, 1, 0), filled.positions)
    # the samples the cameras saw pass through the filler untouched
    np.testing.assert_array_equal(filled.positions[observed], sim.positions[observed])


@pytest.mark.integration
@pytest.mark.xdist_group("exported")  # one worker makes the exports for all three
def test_solved_c3d_holds_joint_centres_that_match_the_bvh(exported: Path) -> None:
    skeleton = SkeletonModel.model_validate_json((exported / "skeleton.json").read_text())
    joints = [j.name for j in skeleton.joints]
    solved = read_markers(exported / "solved.c3d")
    assert list(solved.extra) == joints and len(joints) >= 10

    c3d = ezc3d.c3d(str(exported / "solved.c3d"))
    assert c3d["parameters"]["POINT"]["LABELS"]["value"] == solved.labels + joints
    assert int(c3d["parameters"]["MOCAPFLOW"]["EXTRA_USED"]["value"][0]) == len(joints)
    points, labels = read_with_c3d_package(exported / "solved.c3d")
    assert labels == solved.labels + joints
    centres = np.stack([solved.extra[name] for name in joints], axis=1)
    assert np.isfinite(centres).all()
    np.testing.assert_array_equal(points[:, solved.n_markers:, :3], centres)
    np.testing.assert_array_equal(c3d["data"]["points"][:3, solved.n_markers:].transpose(2, 1, 0), centres)

    bvh = read_bvh(exported / "solved.bvh")
    assert bvh.frames == solved.n_frames and bvh.rate == pytest.approx(RATE, rel=1e-6)
    fk = bvh.forward_kinematics()[:, [bvh.names.index(name) for name in joints]]
    assert np.linalg.norm(fk - centres, axis=-1).max() < 1.0
    names, _, positions = bvhio_positions(exported / "solved.bvh")
    assert np.linalg.norm(positions[:, [names.index(name) for name in joints]] - centres, axis=-1).max() < 1.0


def parse_trc(path: Path) -> tuple[list[str], np.ndarray]:
    """Marker names and (F, N, 3) values of a TRC file by a plain split of its lines (empty cell = NaN)."""
    lines = path.read_text().splitlines()
    names = [cell for cell in lines[3].split("\t")[2:] if cell]
    rows = [[float(cell) if cell else np.nan for cell in line.split("\t")[2:]] for line in lines[5:] if line]
    return names, np.array(rows).reshape(len(rows), len(names), 3)


@pytest.mark.integration
@pytest.mark.xdist_group("exported")  # one worker makes the exports for all three
def test_trc_export_matches_the_c3d_export(exported: Path) -> None:
    c3d = read_markers(exported / "solved.c3d")
    names, values = parse_trc(exported / "solved.trc")
    assert names == c3d.labels + list(c3d.extra) and len(c3d.extra) >= 10
    expected = np.concatenate([c3d.positions, *(p[:, None] for p in c3d.extra.values())], axis=1)
    np.testing.assert_allclose(values, expected, atol=1e-3)  # the C3D holds float32
    trc = read_markers(exported / "solved.trc")  # TRC has no extra points: the joints read back as markers
    assert trc.labels == names and trc.rate == c3d.rate and trc.first_frame == c3d.first_frame
    assert (trc.flags == FLAG_OBSERVED).all()
