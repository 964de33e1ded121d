"""The simulator against its own ground truth: rigs, determinism, rigidity, noise, occlusions, ghosts, hinges, BVH
driving, and the camera model with its single-camera rays."""

from __future__ import annotations

import time
from itertools import combinations, pairwise
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from mocapflow.messages import MarkerFrame, decode, encode
from mocapflow.mocap.rigs import RIG_NAMES, Rig, make_rig
from mocapflow.mocap.simulator import SimFrame, Simulator, SimulatorConfig, simulate, truth_skeleton
from mocapflow.plugins.simulator import SimulatorNode, SimulatorNodeConfig

BVH = Path(__file__).resolve().parents[2] / "shared" / "data" / "cmu_131_01.bvh"


def rest_pose(rig: Rig) -> tuple[np.ndarray, np.ndarray]:
    """Joint origins (S, 3) and marker positions (N, 3) in the rest pose."""
    origin = np.zeros((len(rig.segments), 3))
    for s, p in enumerate(rig.parents):
        origin[s] = rig.joint_offsets[s] + (origin[p] if p >= 0 else 0)
    return origin, rig.marker_offsets + origin[rig.marker_segment]


def pair_distances(points: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """(F, pairs) distances between the markers idx in every frame."""
    return np.stack([np.linalg.norm(points[:, a] - points[:, b], axis=-1) for a, b in combinations(idx, 2)], -1)


# ---------------------------------------------------------------------------------------------------- rigs


@pytest.mark.parametrize("name", RIG_NAMES)
def test_rig_is_a_tree_with_three_or_four_markers_per_segment(name: str) -> None:
    rig = make_rig(name)
    s = len(rig.segments)
    assert rig.parents[0] == -1 and rig.joint_kinds[0] == "free" and rig.joint_names[0] == ""
    assert all(0 <= rig.parents[k] < k for k in range(1, s))  # parents first: a tree reaching every segment
    assert len(set(rig.segments)) == s and len(set(rig.joint_names[1:])) == s - 1
    assert len(set(rig.marker_labels)) == len(rig.marker_labels)
    counts = np.bincount(rig.marker_segment, minlength=s)
    assert counts.min() >= 3 and counts.max() <= 4
    assert set(rig.joint_kinds[1:]) <= {"ball", "hinge"}
    for k in range(1, s):
        norm = np.linalg.norm(rig.hinge_axes[k])
        assert norm == pytest.approx(1.0 if rig.joint_kinds[k] == "hinge" else 0.0)
    origin, markers = rest_pose(rig)
    # Markers sit off the joint centres and are not collinear on any segment.
    assert np.linalg.norm(markers[:, None] - origin[None, 1:], axis=2).min() > 40
    for k in range(s):
        spread = np.linalg.svd(markers[rig.marker_segment == k] - markers[rig.marker_segment == k].mean(0),
                               compute_uv=False)
        assert spread[1] > 25


def test_human_markers_are_off_the_bone_and_limb_clusters_are_not_coplanar() -> None:
    rig = make_rig("human")
    origin, markers = rest_pose(rig)
    assert len(rig.segments) == 15 and {"left_knee", "right_elbow"} <= set(rig.joint_names)
    for s in range(1, len(rig.segments)):
        children = np.flatnonzero(rig.parents == s)
        if len(children) != 1:
            continue
        axis = (origin[children[0]] - origin[s]) / np.linalg.norm(origin[children[0]] - origin[s])
        rel = markers[rig.marker_segment == s] - origin[s]
        off_axis = np.linalg.norm(rel - np.outer(rel @ axis, axis), axis=1)
        assert off_axis.min() >= 40 and off_axis.max() <= 120, rig.segments[s]
    for s in np.flatnonzero(np.bincount(rig.marker_segment) == 4):
        rel = markers[rig.marker_segment == s] - markers[rig.marker_segment == s].mean(0)
        assert np.linalg.svd(rel, compute_uv=False)[2] > 10, rig.segments[s]
    height = markers[:, 2].max() - markers[:, 2].min()
    assert 1600 < height < 1900
    knees = [rig.joint_names.index(n) for n in ("left_knee", "right_knee", "left_elbow", "right_elbow")]
    assert all(rig.joint_kinds[k] == "hinge" for k in knees)


def test_rods_middle_rod_is_359_mm_between_its_joints() -> None:
    rig = make_rig("rods")
    assert len(rig.segments) == 3 and set(rig.joint_kinds[1:]) == {"ball"}
    ends = rig.joint_offsets[rig.parents == 0]  # both joints sit on the middle rod, the root
    assert len(ends) == 2 and np.linalg.norm(ends[0] - ends[1]) == pytest.approx(359.0)


def test_quadruped_topology_differs_from_the_human() -> None:
    human, dog = make_rig("human"), make_rig("quadruped")
    degrees = [sorted(np.bincount(r.parents[1:], minlength=len(r.segments))) for r in (human, dog)]
    assert degrees[0] != degrees[1]
    assert np.sum(dog.parents == 0) == 6  # four legs, neck and tail on the trunk


# ---------------------------------------------------------------------------------------------------- config


@pytest.mark.parametrize(
    "values, message",
    [
        ({"rig": "octopus"}, "unknown rig"),
        ({"hidden_segments": ["wing"]}, "not segments"),
        ({"rig": "rods", "bvh": "x.bvh"}, "human rig only"),
        ({"rate": 0}, "greater than 0"),
        ({"noise": 1}, "Extra inputs"),
    ],
)
def test_config_rejects_bad_values(values: dict, message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        SimulatorConfig.model_validate(values)


# ---------------------------------------------------------------------------------------------------- determinism

BUSY = {"noise_mm": 1.0, "skin_mm": 5.0, "dropout_rate": 3.0, "long_gaps": 6.0, "hidden_segments": ["left_forearm"],
        "ghosts": 3.0}


def assert_same(a: SimFrame, b: SimFrame) -> None:
    assert a.frame == b.frame and a.time == b.time and a.labels == b.labels
    for field in ("points", "identity", "true_positions", "visible", "joint_centres"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))


@pytest.mark.parametrize("unlabelled", [False, True])
def test_frames_are_deterministic_and_order_independent(unlabelled: bool) -> None:
    config = SimulatorConfig(unlabelled=unlabelled, seed=7, **BUSY)
    order = [0, 1, 2400, 7, 1_000_000, 2401, 1]
    first = Simulator(config)
    frames = [first.frame(i) for i in order]
    again = Simulator(config)
    for i, f in sorted(zip(order, frames, strict=True), key=lambda x: -x[0]):
        assert_same(f, again.frame(i))
    assert_same(frames[1], frames[-1])
    assert frames[3].time == pytest.approx(7 / config.rate)
    other = Simulator(config.model_copy(update={"seed": 8})).frame(2400)
    assert not np.allclose(other.true_positions, frames[2].true_positions)


def test_a_frame_prepared_ahead_is_the_frame() -> None:
    """``prepare`` works out a frame's block ahead a step at a time, and the next block once the frame's own is done;
    what a frame then is does not change, whatever steps were taken, nor does any frame asked for after it."""
    config = SimulatorConfig(unlabelled=True, seed=7, **BUSY)
    prepared, plain = Simulator(config), Simulator(config)
    for steps, i in zip((1, 3, 10, 2), (64, 2400, 5, 24_000), strict=True):
        for _ in range(steps):
            prepared.prepare(i)
        assert_same(prepared.frame(i), plain.frame(i))
        assert_same(prepared.frame(i + 1), plain.frame(i + 1))
    live, plain = Simulator(config), Simulator(config)
    for i in range(200):  # as a live source: a step after each frame
        live.prepare(i)
        assert_same(live.frame(i), plain.frame(i))
        if i % 64 == 10:  # the next block is ready ten frames into this one
            assert live._ready is not None and live._ready.index == i // 64 + 1


# ---------------------------------------------------------------------------------------------------- truth


@pytest.mark.parametrize("name", RIG_NAMES)
def test_segments_are_rigid_and_joint_centres_fixed_in_both_segments(name: str) -> None:
    rig = make_rig(name)
    sim = Simulator(SimulatorConfig(rig=name, noise_mm=0.0))
    frames = [sim.frame(i) for i in range(0, 48_000, 97)]  # 200 s at 240 Hz
    true = np.stack([f.true_positions for f in frames])
    centres = np.stack([f.joint_centres for f in frames])
    for s in range(len(rig.segments)):
        d = pair_distances(true, np.flatnonzero(rig.marker_segment == s))
        assert np.ptp(d, axis=0).max() < 1e-6, rig.segments[s]
    for j, child in enumerate(range(1, len(rig.segments))):
        for seg in (rig.parents[child], child):
            idx = np.flatnonzero(rig.marker_segment == seg)
            d = np.linalg.norm(true[:, idx] - centres[:, j, None], axis=-1)
            assert np.ptp(d, axis=0).max() < 1e-6, (rig.joint_names[child], rig.segments[seg])
    # The root travels and turns within a capture volume of about 4 m, z up, bodies above the floor.
    assert np.ptp(centres[..., :2], axis=(0, 1)).min() > 1000 and np.ptp(true[..., :2], axis=(0, 1)).max() < 5000
    assert true[..., 2].min() > -50


def relative_rotations(sim: Simulator, frames: range) -> np.ndarray:
    """(F, S, 3) rotation vectors of each segment relative to its parent (the root: its world rotation)."""
    parents = sim.rig.parents
    out = []
    for i in frames:
        rot, _ = sim.segment_poses(i)
        rel = rot.copy()
        rel[1:] = np.swapaxes(rot[parents[1:]], 1, 2) @ rot[1:]
        out.append(Rotation.from_matrix(rel).as_rotvec())
    return np.array(out)


@pytest.mark.parametrize("name", RIG_NAMES)
def test_hinges_are_hinges_and_every_joint_moves_through_a_good_range(name: str) -> None:
    sim = Simulator(SimulatorConfig(rig=name))
    rig = sim.rig
    rotvec = relative_rotations(sim, range(0, 24_000, 20))
    heading = np.unwrap(np.arctan2(*[(Rotation.from_rotvec(rotvec[:, 0]).apply([1, 0, 0]))[:, k] for k in (1, 0)]))
    assert np.degrees(np.ptp(heading)) > 180  # the root turns around
    for s in range(1, len(rig.segments)):
        if rig.joint_kinds[s] == "hinge":
            axis = rig.hinge_axes[s]
            angle = np.degrees(rotvec[:, s] @ axis)
            np.testing.assert_allclose(rotvec[:, s], np.outer(np.radians(angle), axis), atol=1e-9)
            assert angle.min() >= -1e-9 and angle.max() <= 120 + 1e-9
            assert np.ptp(angle) > 0.7 * np.ptp(rig.motion_ranges[s, 0]), rig.joint_names[s]
        else:  # all three degrees of freedom are exercised
            assert np.degrees(rotvec[:, s].std(0)).min() > 4, rig.joint_names[s]


def test_truth_skeleton_reproduces_the_joint_centres_of_every_frame() -> None:
    config = SimulatorConfig(noise_mm=0.0)
    sim = Simulator(config)
    rig = sim.rig
    skeleton = truth_skeleton(rig, sim.frame(100).true_positions)
    assert skeleton.root == "pelvis" and [s.name for s in skeleton.segments] == list(rig.segments)
    segments = {s.name: s for s in skeleton.segments}
    for i in (0, 1234, 9999):
        f = sim.frame(i)
        rot, _ = sim.segment_poses(i)
        pose = {}
        for seg in skeleton.segments:
            idx = [rig.marker_labels.index(m) for m in seg.markers]
            local = np.array(seg.marker_offsets)
            np.testing.assert_allclose(local.mean(0), 0, atol=1e-9)  # origin at the centroid of the markers
            r, _ = Rotation.align_vectors(f.true_positions[idx] - f.true_positions[idx].mean(0), local)
            pose[seg.name] = r.as_matrix(), f.true_positions[idx].mean(0)
        for joint, centre in zip(skeleton.joints, f.joint_centres, strict=True):
            for seg, offset in ((joint.parent, joint.parent_offset), (joint.child, joint.child_offset)):
                r, t = pose[seg]
                np.testing.assert_allclose(r @ offset + t, centre, atol=1e-6)
            if joint.kind == "hinge":
                s = rig.joint_names.index(joint.name)
                world_axis = rot[rig.parents[s]] @ rig.hinge_axes[s]
                np.testing.assert_allclose(pose[joint.parent][0] @ joint.axis, world_axis, atol=1e-9)
        assert len(segments[joint.child].markers) >= 3


# ---------------------------------------------------------------------------------------------------- observation


def test_noise_has_the_configured_sd() -> None:
    rec = simulate(SimulatorConfig(noise_mm=2.0, seed=3), 2000)
    error = rec.positions - rec.true_positions
    assert np.isfinite(error).all()
    np.testing.assert_allclose(error.reshape(-1, 3).std(0), 2.0, rtol=0.02)  # isotropic
    np.testing.assert_allclose(error.reshape(-1, 3).mean(0), 0.0, atol=0.02)
    quiet = simulate(SimulatorConfig(noise_mm=0.0, seed=3), 10)
    np.testing.assert_array_equal(quiet.positions, quiet.true_positions)


@pytest.mark.integration
def test_soft_tissue_artefact_is_smooth_bounded_and_moves_no_joint() -> None:
    rigid = simulate(SimulatorConfig(noise_mm=0.0), 2400)
    soft = simulate(SimulatorConfig(noise_mm=0.0, skin_mm=10.0), 2400)
    np.testing.assert_array_equal(soft.joint_centres, rigid.joint_centres)
    artefact = soft.true_positions - rigid.true_positions
    size = np.linalg.norm(artefact, axis=-1)
    assert 2.0 < np.sqrt((size**2).mean()) < 8.0 and size.max() < 25.0
    assert np.linalg.norm(np.diff(artefact, axis=0), axis=-1).max() < 1.0  # smooth: < 1 mm per frame at 240 Hz
    rig = make_rig("human")
    thigh = np.flatnonzero(rig.marker_segment == rig.segments.index("left_thigh"))
    assert np.ptp(pair_distances(soft.true_positions, thigh), axis=0).max() > 2.0  # no longer rigid


def unlabelled_checks(sim: Simulator, f: SimFrame, noise: float) -> int:
    """Check one unlabelled frame against its truth; return its ghost count."""
    markers = f.identity >= 0
    assert f.labels is None and np.isfinite(f.points).all() and len(f.points) == len(f.identity)
    assert sorted(f.identity[markers]) == list(np.flatnonzero(f.visible))  # each visible marker exactly once
    np.testing.assert_array_less(np.abs(f.points[markers] - f.true_positions[f.identity[markers]]), 6 * noise)
    ghosts = f.points[~markers]
    nearest = np.linalg.norm(ghosts[:, None] - f.true_positions[None], axis=-1).min(1, initial=np.inf)
    assert np.all(nearest <= 300 + 1e-9)
    return int((~markers).sum())


def test_unlabelled_frames_are_shuffled_visible_markers_plus_ghosts() -> None:
    config = SimulatorConfig(unlabelled=True, ghosts=4.0, noise_mm=0.5, dropout_rate=2.0, seed=5)
    sim = Simulator(config)
    frames = [sim.frame(i) for i in range(600)]
    ghosts = [unlabelled_checks(sim, f, 0.5) for f in frames]
    assert np.mean(ghosts) == pytest.approx(4.0, abs=0.3) and np.var(ghosts) == pytest.approx(4.0, rel=0.3)
    orders = {tuple(f.identity[:5]) for f in frames}
    assert len(orders) > 500  # rows are shuffled every frame
    rec = simulate(config, 50)  # the batch form keeps both views, consistent with each other
    assert rec.points is not None and rec.identity is not None
    for i in range(50):
        markers = rec.identity[i] >= 0
        np.testing.assert_array_equal(rec.positions[i, rec.identity[i][markers]], rec.points[i][markers])
        np.testing.assert_array_equal(np.isfinite(rec.positions[i, :, 0]), rec.visible[i])


def test_labelled_frames_have_rows_in_marker_order_and_nan_where_occluded() -> None:
    rec = simulate(SimulatorConfig(dropout_rate=3.0, ghosts=5.0, seed=2), 500)
    assert rec.points is None and rec.identity is None
    assert rec.positions.shape == rec.true_positions.shape == (500, len(rec.labels), 3)
    np.testing.assert_array_equal(np.isnan(rec.positions).any(-1), ~rec.visible)
    assert not rec.visible.all()
    rig = make_rig("human")
    assert rec.marker_segment == [rig.segments[s] for s in rig.marker_segment]
    assert rec.joint_child == list(rig.segments[1:]) and rec.joint_parent[rec.joint_names.index("left_knee")] == (
        "left_thigh")


def runs(hidden: np.ndarray) -> np.ndarray:
    """Lengths of the runs of True in each column of a (F, N) mask, leaving out runs cut by the end of the data."""
    padded = np.pad(hidden, ((1, 1), (0, 0))).astype(np.int8)
    edges = np.diff(padded, axis=0)
    starts, stops = np.nonzero(edges.T == 1), np.nonzero(edges.T == -1)
    whole = stops[1] < len(hidden)
    return (stops[1] - starts[1])[whole]


@pytest.mark.integration
def test_short_dropouts_follow_the_configured_rate() -> None:
    rate, seconds, per_s = 60.0, 200, 2.0
    rec = simulate(SimulatorConfig(rate=rate, dropout_rate=per_s, noise_mm=0.0), int(seconds * rate))
    hidden = ~rec.visible
    mean_length = 6 / rate  # 2-10 frames
    # Poisson starts of random length: busy a fraction 1 - exp(-rate * mean length) of the time, and gaps (merged
    # when they overlap) begin at per_s * exp(-per_s * mean length) per second.
    assert hidden.mean() == pytest.approx(1 - np.exp(-per_s * mean_length), rel=0.05)
    lengths = runs(hidden)
    assert len(lengths) / hidden.shape[1] / seconds == pytest.approx(per_s * np.exp(-per_s * mean_length), rel=0.07)
    assert lengths.min() >= 2 and 4 <= np.median(lengths) <= 8


@pytest.mark.integration
def test_long_gaps_and_hidden_segments_follow_the_configured_rates() -> None:
    rate, seconds = 30.0, 300
    rec = simulate(SimulatorConfig(rate=rate, long_gaps=3.0, hidden_segments=["left_shank", "head"], noise_mm=0.0),
                   int(seconds * rate))
    rig = make_rig("human")
    hidden_seg = np.isin(rig.marker_segment, [rig.segments.index("left_shank"), rig.segments.index("head")])
    others = ~rec.visible[:, ~hidden_seg]
    assert others.mean() == pytest.approx(1 - np.exp(-3.0 / 60 * 2.5), rel=0.15)  # 3 gaps/min of 1-4 s
    gap_s = runs(others) / rate
    assert gap_s.min() >= 1.0 - 1e-9 and np.median(gap_s) == pytest.approx(2.5, abs=0.4)
    for seg in ("left_shank", "head"):
        idx = rig.marker_segment == rig.segments.index(seg)
        together = (~rec.visible[:, idx]).all(1)
        # The whole segment vanishes together for periods of 2-6 s, about a third of the time.
        assert together.mean() == pytest.approx(1 - np.exp(-0.1 * 4), abs=0.12)
        assert np.median(runs(together[:, None])) / rate > 2.0
        assert (~rec.visible[:, idx]).any(1).mean() - together.mean() < 0.3  # its own long gaps come on top


# ---------------------------------------------------------------------------------------------------- BVH driving


@pytest.fixture(scope="module")
def bvh_sim() -> Simulator:
    if not BVH.is_file():
        pytest.skip(f"real data file {BVH} is absent")
    from mocapflow.io.bvh import read_bvh

    bvh = read_bvh(BVH)
    return Simulator(SimulatorConfig(bvh=str(BVH), rate=bvh.rate, noise_mm=0.0), bvh)


def test_bvh_drives_the_human_rig_with_its_own_bones(bvh_sim: Simulator) -> None:
    from mocapflow.io.bvh import read_bvh

    bvh = read_bvh(BVH)
    rig = bvh_sim.rig
    world = bvh.forward_kinematics()
    to_rig = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # BVH y-up to rig z-up
    pairs = {"left_thigh": ("LeftHip", "LeftKnee"), "right_upper_arm": ("RightShoulder", "RightElbow")}
    for i in (0, 300, 993):
        f = bvh_sim.frame(i)
        _, origin = bvh_sim.segment_poses(i)
        for seg, (a, b) in pairs.items():
            s = rig.segments.index(seg)
            child = int(np.flatnonzero(rig.parents == s)[0])
            bone = origin[child] - origin[s]
            assert np.linalg.norm(bone) == pytest.approx(np.linalg.norm(rig.joint_offsets[child]))
            expected = to_rig @ (world[i, bvh.index(b)] - world[i, bvh.index(a)])
            cos = bone @ expected / np.linalg.norm(bone) / np.linalg.norm(expected)
            assert cos > np.cos(np.radians(0.01)), (seg, i)  # the BVH's bone direction, the rig's length
        assert f.true_positions[:, 2].min() > 0
    # Beyond the clip the motion plays backwards, so it never jumps.
    last = bvh.frames - 1
    np.testing.assert_allclose(bvh_sim.frame(last + 40).true_positions, bvh_sim.frame(last - 40).true_positions,
                               atol=1e-6)
    np.testing.assert_allclose(bvh_sim.frame(2 * last + 5).true_positions, bvh_sim.frame(5).true_positions,
                               atol=1e-6)


def test_bvh_motion_keeps_rigid_segments_and_true_hinges(bvh_sim: Simulator) -> None:
    rig = bvh_sim.rig
    frames = range(0, 3000, 7)
    true = np.stack([bvh_sim.frame(i).true_positions for i in frames])
    for s in range(len(rig.segments)):
        assert np.ptp(pair_distances(true, np.flatnonzero(rig.marker_segment == s)), axis=0).max() < 1e-6
    rotvec = relative_rotations(bvh_sim, frames)
    for s in np.flatnonzero(np.array(rig.joint_kinds) == "hinge"):
        axis = rig.hinge_axes[s]
        np.testing.assert_allclose(rotvec[:, s], np.outer(rotvec[:, s] @ axis, axis), atol=1e-9)
        angle = np.degrees(rotvec[:, s] @ axis)
        assert np.percentile(angle, 5) > -5 and angle.max() > 60, rig.joint_names[s]  # flexion is positive


# ---------------------------------------------------------------------------------------------------- cameras


def camera_centres(config: SimulatorConfig) -> np.ndarray:
    """(C, 3) cameras as documented: evenly spaced on a horizontal circle about the origin, the first on +x."""
    azimuth = 2 * np.pi * np.arange(config.cameras) / config.cameras
    r = config.camera_radius_mm
    return np.stack([r * np.cos(azimuth), r * np.sin(azimuth), np.full(config.cameras, config.camera_height_mm)], 1)


def observe(config: SimulatorConfig, frames: range) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points (F, N, 3), rays (F, N, 6), visible (F, N) and true positions (F, N, 3) of the labelled frames."""
    sim = Simulator(config)
    out = [sim.frame(i) for i in frames]
    return tuple(np.stack([getattr(f, k) for f in out]) for k in ("points", "rays", "visible", "true_positions"))


@pytest.mark.parametrize("unlabelled", [False, True])
def test_no_cameras_is_the_simulator_without_a_camera_model(unlabelled: bool) -> None:
    plain = Simulator(SimulatorConfig(unlabelled=unlabelled, seed=7, **BUSY))
    unused = Simulator(SimulatorConfig(unlabelled=unlabelled, seed=7, cameras=0, camera_radius_mm=1000,
                                       camera_dropout=0.5, **BUSY))
    for i in (0, 5, 2400):
        a, b = plain.frame(i), unused.frame(i)
        assert a.rays is None and b.rays is None
        assert_same(a, b)
    assert simulate(SimulatorConfig(**BUSY), 5).rays is None


@pytest.mark.integration
def test_single_camera_markers_arrive_as_rays_through_their_noisy_positions() -> None:
    noise = 0.5
    config = SimulatorConfig(cameras=4, rate=60, noise_mm=noise, seed=3, hidden_segments=["left_forearm"])
    frames = range(0, 3600, 3)  # a minute
    points, rays, visible, true = observe(config, frames)
    bare, _, bare_visible, _ = observe(config.model_copy(update={"cameras": 0}), frames)  # same noise draws
    has_ray = np.isfinite(rays).all(-1)
    assert np.isnan(rays[~has_ray]).all()
    assert np.isnan(points[has_ray]).all() and not visible[has_ray].any()
    np.testing.assert_array_equal(np.isfinite(points).all(-1), visible)
    np.testing.assert_array_equal(points[visible], bare[visible])  # points are observed as without cameras
    origin, direction = rays[has_ray][:, :3], rays[has_ray][:, 3:]
    cameras = camera_centres(config)
    assert np.linalg.norm(origin[:, None] - cameras[None], axis=-1).min(1).max() < 1e-9
    np.testing.assert_allclose(np.linalg.norm(direction, axis=1), 1.0, atol=1e-12)

    def off_ray(x: np.ndarray) -> np.ndarray:
        rel = x - origin
        along = (rel * direction).sum(1)
        assert along.min() > 1000  # towards the marker, away from the camera
        return np.linalg.norm(rel - along[:, None] * direction, axis=1)

    assert off_ray(bare[has_ray]).max() < 1e-6  # through the noisy position a point would have had
    assert off_ray(true[has_ray]).max() < 5 * noise
    # A marker hidden by a schedule is seen by no camera; without cameras every other marker would be a point.
    assert (~bare_visible).sum() > 100
    assert not (has_ray | visible)[~bare_visible].any()
    assert not (visible & ~bare_visible).any()
    # A realistic mix: most markers are points, a few are rays, fewer are missing (none missing without cameras
    # outside the hidden periods).
    point, ray = visible[bare_visible].mean(), has_ray[bare_visible].mean()
    missing = 1 - point - ray
    assert point > 0.9 and 0.01 < ray < 0.1 and 0.0005 < missing < ray


def test_camera_frames_are_deterministic_and_order_independent() -> None:
    config = SimulatorConfig(cameras=3, camera_dropout=0.2, seed=4, **BUSY)
    order = [0, 1, 2400, 7, 2401, 1]
    first = Simulator(config)
    frames = [first.frame(i) for i in order]
    again = Simulator(config)
    for i, f in sorted(zip(order, frames, strict=True), key=lambda x: -x[0]):
        g = again.frame(i)
        assert_same(f, g)
        np.testing.assert_array_equal(f.rays, g.rays)
    assert np.isfinite(frames[2].rays).all(1).any()


def test_one_camera_gives_no_points_and_the_camera_misses_markers_at_random() -> None:
    frames = range(0, 3000, 10)
    points, rays, visible, _ = observe(SimulatorConfig(cameras=1, rate=60, seed=5), frames)
    has_ray = np.isfinite(rays).all(-1)
    assert not visible.any() and np.isnan(points).all()
    assert 0.5 < has_ray.mean() < 0.9  # the rest is hidden by the body or out of view
    config = SimulatorConfig(cameras=4, rate=60, seed=5)
    _, _, seen_points, _ = observe(config, frames)
    _, dropped_rays, dropped_points, _ = observe(config.model_copy(update={"camera_dropout": 0.3}), frames)
    assert not (dropped_points & ~seen_points).any()  # a camera missing a marker only removes observations
    assert dropped_points.mean() < seen_points.mean() - 0.1 and np.isfinite(dropped_rays).all(-1).mean() > 0.1
    _, none_rays, none_points, _ = observe(config.model_copy(update={"camera_dropout": 1.0}), range(5))
    assert not none_points.any() and np.isnan(none_rays).all()


@pytest.mark.integration
def test_more_cameras_see_more() -> None:
    """2C cameras include the C cameras of the smaller ring: every marker seen as a point stays a point, every marker
    observed at all stays observed, and the share of rays and missing markers falls."""
    frames = range(0, 12000, 20)
    previous, unseen = None, []
    for cameras in (1, 2, 4, 8):
        _, rays, visible, _ = observe(SimulatorConfig(cameras=cameras, rate=60, seed=6), frames)
        observed = visible | np.isfinite(rays).all(-1)
        if previous is not None:
            assert not (previous[0] & ~visible).any() and not (previous[1] & ~observed).any()
        previous = visible, observed
        unseen.append(1 - visible.mean())
    assert all(a > b for a, b in pairwise(unseen)) and unseen[-1] < 0.01


def test_capsules_sit_just_inside_the_markers() -> None:
    for name in RIG_NAMES:
        rig = make_rig(name)
        sim = Simulator(SimulatorConfig(rig=name, cameras=1))
        for s in range(len(rig.segments)):
            children = np.flatnonzero(rig.parents == s)
            local = rig.marker_offsets[rig.marker_segment == s]
            end = sim.capsule_ends[s]
            if len(children):
                np.testing.assert_array_equal(end, rig.joint_offsets[children[0]])
            else:  # a leaf: along its markers' centroid, a little beyond
                centroid = local.mean(0)
                assert np.linalg.norm(np.cross(end, centroid)) < 1e-9 * np.linalg.norm(end) ** 2
                assert 1.1 < np.linalg.norm(end) / np.linalg.norm(centroid) < 1.5
            along = np.clip(local @ end / (end @ end), 0, 1)
            skin = np.linalg.norm(local - along[:, None] * end, axis=1)
            assert 0.6 * skin.min() < sim.capsule_radii[s] < 0.95 * skin.min(), (name, rig.segments[s])


@pytest.mark.integration
def test_a_line_of_sight_through_a_capsule_hides_the_marker() -> None:
    """One camera, no noise: a marker is a ray exactly when, by brute force over points every 0.5 mm along every
    capsule's axis, its line of sight (beyond the first 5 mm) misses every capsule and the marker is in the camera's
    35-degree cone. Cases within 0.5 mm or 0.01 degree of the boundary are left out. The camera stands close, so
    that the body also leaves its cone."""
    config = SimulatorConfig(cameras=1, camera_radius_mm=2500, rate=60, noise_mm=0.0, seed=8)
    sim = Simulator(config)
    rig = sim.rig
    camera = camera_centres(config)[0]
    view = np.array([0.0, 0.0, 1000.0]) - camera
    view /= np.linalg.norm(view)
    counts = {"seen": 0, "own": 0, "other": 0, "out of view": 0}
    for i in range(0, 12000, 200):
        f = sim.frame(i)
        rot, pos = sim.segment_poses(i)
        ray = np.isfinite(f.rays).all(1)
        m = f.true_positions
        sight = camera - m
        length = np.linalg.norm(sight, axis=1)
        angle = np.degrees(np.arccos(sight @ -view / length))
        start = m + 5 * sight / length[:, None]
        gap = np.full((len(m), len(rig.segments)), np.inf)
        for s in range(len(rig.segments)):
            end = pos[s] + rot[s] @ sim.capsule_ends[s]
            axis = pos[s] + np.linspace(0, 1, int(np.linalg.norm(end - pos[s]) / 0.5) + 2)[:, None] * (end - pos[s])
            rel = axis[None] - start[:, None]  # (N, samples, 3)
            d = (camera - start)[:, None]
            t = np.clip((rel * d).sum(-1) / (d * d).sum(-1), 0, 1)
            gap[:, s] = np.linalg.norm(rel - t[..., None] * d, axis=-1).min(1)
        clearance = gap - sim.capsule_radii
        clear = np.abs(clearance).min(1) > 0.5
        clear &= np.abs(angle - 35) > 0.01
        blocked = (clearance < 0).any(1)
        in_view = angle < 35
        np.testing.assert_array_equal(ray[clear], (in_view & ~blocked)[clear], err_msg=f"frame {i}")
        counts["seen"] += (ray & clear).sum()
        counts["out of view"] += (~in_view & clear).sum()
        own = clearance[np.arange(len(m)), rig.marker_segment] < 0
        counts["own"] += (in_view & own & clear).sum()
        counts["other"] += (in_view & blocked & ~own & clear).sum()
    assert min(counts.values()) > 20, counts  # every case is exercised


@pytest.mark.parametrize("unlabelled", [False, True])
def test_simulator_node_publishes_the_rays(unlabelled: bool) -> None:
    config = SimulatorNodeConfig(cameras=3, rate=60, seed=9, frames=40, unlabelled=unlabelled)
    sent: list[tuple[str, MarkerFrame]] = []
    node = SimulatorNode(config, lambda port, msg: sent.append((port, msg)))
    index = 0
    while node.emit(index):
        index += 1
    markers = [msg for port, msg in sent if port == "markers"]
    assert index == 40 and len(markers) == 40
    sim = Simulator(SimulatorConfig(cameras=3, rate=60, seed=9, unlabelled=unlabelled))
    labelled_sim = Simulator(SimulatorConfig(cameras=3, rate=60, seed=9))
    for message in markers:
        back = decode(encode(message), MarkerFrame)
        frame = sim.frame(message.frame)
        np.testing.assert_allclose(back.rays, frame.rays, rtol=1e-6, atol=1e-3)  # float32 on the wire, NaN kept
        ray = np.isfinite(back.rays).all(1)
        assert np.isnan(back.positions[ray]).all()  # a ray's row has no position
        if unlabelled:  # extra rows after the points: the labelled stream's rays, one per single-camera marker
            assert not np.isnan(back.positions[~ray]).any() and ray[len(ray) - ray.sum():].all()
            labelled = labelled_sim.frame(message.frame)
            np.testing.assert_array_equal(np.sort(frame.identity[ray]),
                                          np.flatnonzero(np.isfinite(labelled.rays).all(1)))
            np.testing.assert_array_equal(frame.rays[ray], labelled.rays[frame.identity[ray]])
        else:
            np.testing.assert_array_equal(np.isnan(back.positions).any(1), ~frame.visible)
    assert sum(np.isfinite(m.rays).all(1).sum() for m in markers) > 20


def test_a_simulated_frame_is_stamped_with_the_time_it_was_due() -> None:
    """Latency counts from when a frame was due on the source's timetable, so a frame emitted late (its process busy)
    shows as late; outside a run, when it is made."""
    sent: list[Any] = []
    node = SimulatorNode(SimulatorNodeConfig(rig="rods", rate=100), lambda port, msg: sent.append(msg), "tracker")
    before = time.time_ns()
    node.emit(3)
    assert before <= sent[0].capture_ns <= time.time_ns()
    node.clock_origin_ns = 10**18  # as the runtime sets it: frame 0 due then
    node.emit(250)
    assert sent[-1].frame == 250 and sent[-1].capture_ns == 10**18 + 2_500_000_000
    assert all(m.capture_ns == sent[-1].capture_ns for m in sent[2:])  # the truth carries the same stamp
