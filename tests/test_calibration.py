"""Skeleton generation end to end: simulated rigs against their truth, the real lower-body file against its expert
model, the errors a user can act on, the solver with gaps, and the calibrate and solve commands."""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocapflow.errors import CalibrationError
from mocapflow.mocap.calibration import build_skeleton, calibrate
from mocapflow.mocap.model import SkeletonModel
from mocapflow.mocap.rigid import bone_lengths, fit_shape
from mocapflow.mocap.simulator import SimRecording, SimulatorConfig, simulate
from mocapflow.mocap.solve import solve


@cache
def _recording(rig: str, frames: int = 2000, **options: float) -> SimRecording:
    return simulate(SimulatorConfig(rig=rig, rate=120, noise_mm=0.5, seed=7, **options), frames)


@cache
def _skeleton(rig: str, joint_method: str) -> SkeletonModel:
    rec = _recording(rig)
    return calibrate(rec.positions, rec.labels, rec.rate, joint_method=joint_method)


def _true_segment(rec: SimRecording, skeleton: SkeletonModel) -> dict[str, str]:
    """The rig segment each calibrated segment stands for (by its first marker)."""
    of = dict(zip(rec.labels, rec.marker_segment, strict=True))
    return {s.name: of[s.markers[0]] for s in skeleton.segments}


def _true_segments(rec: SimRecording) -> list[list[str]]:
    """The rig's segments, each as its sorted marker labels, sorted."""
    of = dict(zip(rec.labels, rec.marker_segment, strict=True))
    return sorted(sorted(label for label in rec.labels if of[label] == s) for s in set(rec.marker_segment))


def _joint_errors(rec: SimRecording, skeleton: SkeletonModel, positions: np.ndarray | None = None) -> dict:
    """Mean distance (mm) between solved and true joint centres, per true joint name, with the joint's kind."""
    seg = _true_segment(rec, skeleton)
    pose = solve(skeleton, rec.positions if positions is None else positions, rec.labels)
    truth = {frozenset(pc): k for k, pc in enumerate(zip(rec.joint_parent, rec.joint_child, strict=True))}
    errors = {}
    for j, joint in enumerate(skeleton.joints):
        k = truth[frozenset((seg[joint.parent], seg[joint.child]))]
        error = np.linalg.norm(pose.joint_centres[:, j] - rec.joint_centres[:, k], axis=1)
        errors[rec.joint_names[k]] = (joint.kind, float(np.nanmean(error)))
    return errors


@pytest.mark.parametrize(("rig", "joint_method"), [("human", "variance"), ("rods", "variance"),
                                                   ("quadruped", "variance"), ("human", "closed-form")])
@pytest.mark.integration
def test_simulated_rigs_give_their_true_segments_tree_and_joints(rig: str, joint_method: str) -> None:
    rec = _recording(rig)
    skeleton = _skeleton(rig, joint_method)
    assert sorted(sorted(s.markers) for s in skeleton.segments) == _true_segments(rec)
    seg = _true_segment(rec, skeleton)
    assert {frozenset((seg[j.parent], seg[j.child])) for j in skeleton.joints} == {
        frozenset(pc) for pc in zip(rec.joint_parent, rec.joint_child, strict=True)}
    errors = _joint_errors(rec, skeleton)
    hinges = {rec.joint_names[k] for k, c in enumerate(rec.joint_child) if _kind(rig, c) == "hinge"}
    assert {name for name, (kind, _) in errors.items() if kind == "hinge"} == hinges
    ball = [e for kind, e in errors.values() if kind == "ball"]
    assert np.mean(ball) < 5.0 and max(ball) < 5.0
    assert all(e < 10.0 for kind, e in errors.values() if kind == "hinge")  # placed level with their neighbours


def _kind(rig: str, segment: str) -> str:
    from mocapflow.mocap.rigs import make_rig

    r = make_rig(rig)
    return r.joint_kinds[r.segments.index(segment)]


def test_a_few_wrong_samples_cost_no_segment() -> None:
    """Two ghosts each taken for a head marker in one frame (as a labeller under heavy ghosts may) make the head's
    pairs look loose to a plain standard deviation; the skeleton still has the head."""
    rec = _recording("quadruped")
    positions = rec.positions.copy()
    head = [rec.labels.index(label) for label in ("HED1", "HED2")]
    positions[500, head[0]] += [180.0, 0.0, 0.0]
    positions[900, head[1]] += [0.0, -160.0, 30.0]
    skeleton = calibrate(positions, rec.labels, rec.rate)
    assert sorted(sorted(s.markers) for s in skeleton.segments) == _true_segments(rec)


def test_two_subjects_captured_together_give_the_skeleton_of_one_naming_the_other(
        caplog: pytest.LogCaptureFixture) -> None:
    """A quadruped and a human (their skin moving 3 mm over the human's muscles) captured together, 3 m apart, each
    marker labelled with its subject's prefix. Their distances spread by hundreds of millimetres: the two move on
    their own. Each is grouped into segments at its own noise, as if captured alone, and the skeleton is one
    subject's tree, the other's markers named in a warning: a joint never joins two subjects."""
    animal = _recording("quadruped")
    person = simulate(SimulatorConfig(rig="human", rate=120, noise_mm=0.5, skin_mm=3.0, seed=8), len(animal.positions))
    positions = np.concatenate([animal.positions, person.positions + [3000.0, 0.0, 0.0]], axis=1)
    labels = [f"Dog:{m}" for m in animal.labels] + [f"Ann:{m}" for m in person.labels]
    skeleton = calibrate(positions, labels, animal.rate)
    alone = calibrate(person.positions, person.labels, person.rate)
    segments = sorted(sorted(s.markers) for s in skeleton.segments)
    assert all(m.startswith("Ann:") for segment in segments for m in segment)  # the subject with most markers
    assert segments == sorted(sorted(f"Ann:{m}" for m in s.markers) for s in alone.segments)
    assert len(skeleton.joints) == len(alone.joints)
    assert f"left out {len(animal.labels)} markers that move on their own" in caplog.text


def test_rods_middle_length() -> None:
    lengths = bone_lengths(_skeleton("rods", "variance"))
    assert len(lengths) == 1
    assert abs(next(iter(lengths.values())) - 359.0) < 0.005 * 359.0


def test_hinge_axes_are_reported_in_the_parent_frame() -> None:
    rec = _recording("human")
    skeleton = _skeleton("human", "closed-form")
    seg = _true_segment(rec, skeleton)
    from mocapflow.mocap.rigs import make_rig

    rig = make_rig("human")
    pose = solve(skeleton, rec.positions[:1], rec.labels)
    names = [s.name for s in skeleton.segments]
    for joint in (j for j in skeleton.joints if j.kind == "hinge"):
        child = rig.segments.index(seg[joint.child])
        parent_world = Rotation.from_quat(pose.rotations[0, names.index(joint.parent)])
        # the rig's axis is in the parent's rig frame; compare directions in the world at frame 0
        true_world = Rotation.from_matrix(_rig_parent_rotation(rec, rig, child)).apply(rig.hinge_axes[child])
        assert abs(abs(parent_world.apply(joint.axis) @ true_world) - 1) < 0.01


def _rig_parent_rotation(rec: SimRecording, rig: object, child: int) -> np.ndarray:
    """World rotation of a rig segment's parent at frame 0, from its true markers and rig marker offsets."""
    parent = rig.parents[child]
    idx = np.flatnonzero(rig.marker_segment == parent)
    local = rig.marker_offsets[idx] - rig.marker_offsets[idx].mean(0)
    world = rec.true_positions[0, idx] - rec.true_positions[0, idx].mean(0)
    return Rotation.align_vectors(world, local)[0].as_matrix()


@pytest.mark.integration
def test_calibration_and_solver_work_through_gaps() -> None:
    gappy = _recording("human", dropout_rate=0.5, long_gaps=4.0)
    assert np.isnan(gappy.positions).mean() > 0.05
    skeleton = calibrate(gappy.positions, gappy.labels, gappy.rate, joint_method="closed-form")
    of = dict(zip(gappy.labels, gappy.marker_segment, strict=True))
    seg = _true_segment(gappy, skeleton)
    assert {frozenset((seg[j.parent], seg[j.child])) for j in skeleton.joints} == {
        frozenset(pc) for pc in zip(gappy.joint_parent, gappy.joint_child, strict=True)}
    assert all(len({of[m] for m in s.markers}) == 1 for s in skeleton.segments)
    errors = _joint_errors(gappy, skeleton)
    assert max(e for _, e in errors.values()) < 5.0
    pose = solve(skeleton, gappy.positions, gappy.labels)
    assert np.isfinite(pose.joint_centres).all(-1).mean() > 0.99


def test_local_rotations_are_relative_to_the_parent() -> None:
    rec = _recording("rods")
    skeleton = _skeleton("rods", "variance")
    pose = solve(skeleton, rec.positions[:50], rec.labels)
    local = pose.local_rotations()
    root = [s.name for s in skeleton.segments].index(skeleton.root)
    assert np.allclose(np.abs((local[:, root] * pose.rotations[:, root]).sum(-1)), 1.0)
    for child, parent in enumerate(pose.parents):
        if parent >= 0:
            expected = (Rotation.from_quat(pose.rotations[:, parent]).inv()
                        * Rotation.from_quat(pose.rotations[:, child]))
            assert (Rotation.from_quat(local[:, child]) * expected.inv()).magnitude().max() < 1e-9


def _leg(frames: int = 1500, seed: int = 3) -> tuple[np.ndarray, list[str], list[np.ndarray], Rotation]:
    """Pelvis, thigh, shank and foot (4 markers each, the limb clusters on the outside) joined by a ball hip, a knee
    flexing 0-70 deg with +-5 deg of other rotations, and a ball ankle; the thigh cluster slides 6 mm with the knee
    angles (soft tissue). Hip, knee and ankle centres are on the limb's line, the knee axis is the thigh's x.
    Returns positions, labels, the true hip, knee and ankle centres, and the thigh's rotations."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / 100.0

    def smooth(amplitude: float) -> Rotation:
        f, phase = rng.uniform(0.2, 1.0, (3, 3)), rng.uniform(0, 2 * np.pi, (3, 3))
        return Rotation.from_rotvec(amplitude * np.sin(t[:, None, None] * 2 * np.pi * f + phase).sum(1) / np.sqrt(3))

    flexion = np.radians(35) * (1 - np.cos(2 * np.pi * 0.7 * t))
    other = np.radians(5) * np.sin(2 * np.pi * np.outer(t, [0.9, 1.3]) + [0.4, 2.0])
    pelvis = smooth(0.2)
    turns = [pelvis, pelvis * smooth(0.4)]
    turns += [turns[1] * Rotation.from_rotvec(np.column_stack([flexion, other]))]
    turns += [turns[2] * smooth(0.25)]
    joints = [np.array([90.0, 0, -60]), np.array([0, 0, -420.0]), np.array([0, 0, -400.0])]  # in the parent frame
    origins = [np.column_stack([300 * np.sin(t), 200 * np.cos(0.7 * t), 1000 + 20 * np.sin(3 * t)])]
    for k, joint in enumerate(joints):  # each child's frame has its origin at its joint with the parent
        origins.append(turns[k].apply(joint) + origins[k])
    clusters = [[[80, 60, 0], [-80, 60, 0], [70, -70, 20], [-70, -70, 20]],
                [[70, 20, -120], [80, -20, -200], [60, 30, -280], [75, 0, -330]],
                [[60, 20, -100], [70, -25, -180], [55, 25, -260], [65, 0, -320]],
                [[30, 80, -60], [-30, 90, -60], [0, -50, -70], [0, 150, -70]]]
    skin = 6.0 * np.column_stack([np.sin(flexion), other / np.radians(5)])
    positions = []
    for k, cluster in enumerate(clusters):
        local = np.asarray(cluster, float)[None] + (skin[:, None] if k == 1 else 0.0)
        positions.append(np.einsum("fab,fnb->fna", turns[k].as_matrix(), np.broadcast_to(local, (frames, 4, 3)))
                         + origins[k][:, None])
    positions = np.concatenate(positions, 1) + rng.normal(size=(frames, 16, 3)) * 0.5
    labels = [f"{s}{i}" for s in ("PEL", "THI", "SHK", "FT") for i in range(1, 5)]
    return positions, labels, origins[1:], turns[1]


def test_a_near_hinge_is_placed_level_with_its_neighbours() -> None:
    """A knee whose other rotations are too small for its skin artefact: the closed form puts it 20 mm off along
    the flexion axis, calibration recognises a hinge and puts it level with the hip and the ankle."""
    from mocapflow.mocap.cor import SequentialCoR

    positions, labels, (hip, knee, ankle), thigh = _leg()
    cor = SequentialCoR()
    cor.update_markers(positions[:, 4:8], positions[:, 8:12])
    assert not cor.estimate().is_hinge
    groups = [list(range(4 * k, 4 * k + 4)) for k in range(4)]
    axis = thigh.apply([1.0, 0.0, 0.0])
    along = {}
    for placement in ("neighbours", "estimator"):
        skeleton = build_skeleton(positions, labels, 100.0, groups, hinge_placement=placement)
        assert {(j.parent, j.child): j.kind for j in skeleton.joints} == {
            ("THI", "PEL"): "ball", ("THI", "SHK"): "hinge", ("SHK", "FT"): "ball"}
        pose = solve(skeleton, positions, labels)
        centres = dict(zip(pose.joint_names, pose.joint_centres.transpose(1, 0, 2), strict=True))
        along[placement] = abs(np.einsum("fa,fa->f", centres["THI-SHK"] - knee, axis).mean())
        for name, truth in (("THI-PEL", hip), ("SHK-FT", ankle)):
            assert np.linalg.norm(centres[name] - truth, axis=1).mean() < 5.0
    assert along["estimator"] > 15.0 and along["neighbours"] < 3.0


def test_real_lower_body_gives_the_expert_segments_and_tree(data_dir: Path) -> None:
    from mocapflow.io.markers import read_markers

    data = read_markers(data_dir / "lowerbody_clusters_knee_0401.c3d")
    skeleton = calibrate(data.positions, data.labels, data.rate)
    part = {label: s.name for s in skeleton.segments for label in s.markers}
    pelvis, trunk = part["LASI"], part["CLAV"]
    assert sorted(m for m in part if part[m] == pelvis) == sorted(["LASI", "RASI", "LPSI", "RPSI"])
    assert sorted(m for m in part if part[m] == trunk) == sorted(["LSHL", "CLAV", "RSHL", "C7"])
    edges = {frozenset((j.parent, j.child)) for j in skeleton.joints}
    expected = {frozenset((pelvis, trunk))}
    for side in "LR":
        thigh, shank, foot = part[f"{side}TH1"], part[f"{side}SH1"], part[f"{side}TOE"]
        assert len({thigh, shank, foot, pelvis}) == 4
        assert {m for m in part if part[m] == thigh} == {f"{side}TH{i}" for i in range(1, 5)}
        assert {f"{side}SH{i}" for i in range(1, 5)} <= {m for m in part if part[m] == shank}
        expected |= {frozenset((pelvis, thigh)), frozenset((thigh, shank)), frozenset((shank, foot))}
    assert edges == expected
    assert skeleton.root == pelvis
    # knees (hinges, placed level with hip and ankle) and ankles near the midpoints of their two markers: the
    # closed form's own knee point is 41-46 mm away, 33-37 mm of it along the flexion axis
    pose = solve(skeleton, data.positions, data.labels)
    landmarks = (("hinge", "TH1", "SH1", ("MKN", "LKN")), ("ball", "SH1", "TOE", ("LAK", "MAK")))
    for side in "LR":
        for kind, parent, child, pair in landmarks:
            ends = {part[side + parent], part[side + child]}
            j = next(k for k, x in enumerate(skeleton.joints) if {x.parent, x.child} == ends)
            assert skeleton.joints[j].kind == kind
            a, b = (data.positions[:, data.labels.index(side + m)] for m in pair)
            assert np.nanmean(np.linalg.norm(pose.joint_centres[:, j] - (a + b) / 2, axis=1)) < 32.0


def test_an_unlabelled_recording_is_an_error_saying_to_label_it_first() -> None:
    rec = simulate(SimulatorConfig(rig="human", rate=120, seed=2, unlabelled=True), 600)
    width = max(len(p) for p in rec.points)
    points = np.full((len(rec.points), width, 3), np.nan)
    for f, p in enumerate(rec.points):
        points[f, : len(p)] = p
    with pytest.raises(CalibrationError, match="looks unlabelled.*mocapflow label"):
        calibrate(points, [f"point{i}" for i in range(width)], rec.rate)


def test_too_few_frames_is_an_error() -> None:
    rec = _recording("rods")
    with pytest.raises(CalibrationError, match="frames"):
        calibrate(rec.positions[:20], rec.labels, rec.rate)


def test_a_segment_of_one_marker_is_left_out_naming_it(caplog: pytest.LogCaptureFixture) -> None:
    rec = _recording("rods")
    groups = [[i for i, s in enumerate(rec.marker_segment) if s == seg] for seg in ("rod1", "rod2", "rod3")]
    lone = groups[2].pop()  # rod3 keeps its other markers; the one taken off is a segment of its own
    with caplog.at_level("WARNING"):
        skeleton = build_skeleton(rec.positions, rec.labels, rec.rate, [*groups, [lone]])
    assert [r.getMessage() for r in caplog.records if rec.labels[lone] in r.getMessage()]
    assert len(skeleton.segments) == 3 and rec.labels[lone] not in {m for s in skeleton.segments for m in s.markers}
    assert {frozenset((j.parent, j.child)) for j in skeleton.joints} == {
        frozenset((skeleton.segments[0].name, skeleton.segments[1].name)),
        frozenset((skeleton.segments[1].name, skeleton.segments[2].name))}


def test_a_segment_never_seen_whole_is_still_measured() -> None:
    """Each marker of the left thigh is hidden in turn, so that no frame shows the whole thigh: its shape comes from
    the frames that show each part, and the skeleton equals the one from complete data."""
    rec = _recording("human")
    thigh = [i for i, s in enumerate(rec.marker_segment) if s == "left_thigh"]
    gappy = rec.positions.copy()
    for k, frames in enumerate(np.array_split(np.arange(len(gappy)), len(thigh))):
        gappy[frames, thigh[k]] = np.nan
    assert not np.isfinite(gappy[:, thigh]).all((1, 2)).any()
    complete = _skeleton("human", "closed-form")
    skeleton = calibrate(gappy, rec.labels, rec.rate, joint_method="closed-form")
    assert sorted(sorted(s.markers) for s in skeleton.segments) == sorted(sorted(s.markers) for s in complete.segments)
    lengths, truth = bone_lengths(skeleton), bone_lengths(complete)
    assert lengths.keys() == truth.keys()
    assert all(abs(lengths[k] - truth[k]) < 2.0 for k in truth)


def test_closed_form_needs_three_markers_per_segment() -> None:
    rec = _recording("rods")
    groups = [[i for i, s in enumerate(rec.marker_segment) if s == seg] for seg in ("rod1", "rod2", "rod3")]
    groups[2] = groups[2][:2]
    with pytest.raises(CalibrationError, match="fewer than 3 markers"):
        build_skeleton(rec.positions, rec.labels, rec.rate, groups, "closed-form")
    # the default falls back to the distance-variance cost, which needs no segment orientation
    skeleton = build_skeleton(rec.positions, rec.labels, rec.rate, groups)
    assert {frozenset((j.parent, j.child)) for j in skeleton.joints} == {
        frozenset((skeleton.segments[0].name, skeleton.segments[1].name)),
        frozenset((skeleton.segments[1].name, skeleton.segments[2].name))}


def test_a_marker_seen_too_rarely_is_left_out_of_its_segment(caplog: pytest.LogCaptureFixture) -> None:
    """A live clusterer may put a short-lived track (a ghost confirmed, then gone) in a segment: the skeleton is built
    without it, from the markers that fix the segment's orientation, rather than refused."""
    rec = _recording("rods")
    groups = [[i for i, s in enumerate(rec.marker_segment) if s == seg] for seg in ("rod1", "rod2", "rod3")]
    rare = np.full((len(rec.positions), 1, 3), np.nan)
    rare[:50, 0] = rec.positions[:50, groups[2][0]] + 40.0  # seen in 50 of 2000 frames
    positions = np.concatenate([rec.positions, rare], axis=1)
    groups[2].append(len(rec.labels))
    with caplog.at_level("WARNING"):
        skeleton = build_skeleton(positions, [*rec.labels, "GHOST"], rec.rate, groups, "closed-form")
    assert "GHOST" in caplog.text
    assert "GHOST" not in {m for segment in skeleton.segments for m in segment.markers}
    truth = build_skeleton(rec.positions, rec.labels, rec.rate, groups[:2] + [groups[2][:-1]], "closed-form")
    assert skeleton.model_dump() == truth.model_dump()


def test_calibrate_names_a_rarely_seen_marker_once(caplog: pytest.LogCaptureFixture) -> None:
    rec = _recording("rods")
    rare = np.full((len(rec.positions), 1, 3), np.nan)
    rare[:50, 0] = rec.positions[:50, 0] + 40.0
    with caplog.at_level("WARNING"):
        calibrate(np.concatenate([rec.positions, rare], axis=1), [*rec.labels, "GHOST"], rec.rate)
    assert len([r for r in caplog.records if "GHOST" in r.getMessage()]) == 1


def test_a_rarely_seen_marker_is_named_once_when_the_build_starts_again(caplog: pytest.LogCaptureFixture) -> None:
    """A pair of markers never seen with the rest makes the build start again without it: the marker seen too rarely
    is still named once, and the skeleton is the rods'."""
    rec = _recording("rods")
    groups = [[i for i, s in enumerate(rec.marker_segment) if s == seg] for seg in ("rod1", "rod2", "rod3")]
    n = len(rec.labels)
    positions = rec.positions.copy()
    positions[:300] = np.nan  # the rods hidden while the pair is seen
    extra = np.full((len(positions), 3, 3), np.nan)
    extra[:300, 0] = rec.positions[:300, 0]
    extra[:300, 1] = rec.positions[:300, 0] + 50.0
    extra[400:450, 2] = rec.positions[400:450, 0] + 40.0  # seen in 50 of 2000 frames
    with caplog.at_level("WARNING"):
        skeleton = build_skeleton(np.concatenate([positions, extra], axis=1), [*rec.labels, "PA", "PB", "GHOST"],
                                  rec.rate, [*groups, [n, n + 1], [n + 2]])
    assert any("PA, PB: never seen long enough together" in r.getMessage() for r in caplog.records)
    assert len([r for r in caplog.records if "GHOST" in r.getMessage()]) == 1
    assert sorted(m for segment in skeleton.segments for m in segment.markers) == sorted(rec.labels)


def test_a_joint_with_too_little_motion_is_reported_and_placed_between_the_segments(
        caplog: pytest.LogCaptureFixture) -> None:
    rec = _recording("rods")
    idx = {seg: [i for i, s in enumerate(rec.marker_segment) if s == seg] for seg in ("rod1", "rod2", "rod3")}
    positions = rec.positions.copy()
    # rod3 barely turns against rod2: its markers follow rod2 with a 1 degree wobble about the true joint
    true = rec.true_positions
    ref2 = true[0, idx["rod2"]] - true[0, idx["rod2"]].mean(0)
    centre = rec.joint_centres[:, rec.joint_child.index("rod3")]
    local3 = true[0, idx["rod3"]] - centre[0]
    wobble = Rotation.from_rotvec(np.outer(np.sin(np.arange(len(true)) / 20), [0, 0, np.radians(1.0)]))
    for f in range(len(true)):
        turn, _ = Rotation.align_vectors(true[f, idx["rod2"]] - true[f, idx["rod2"]].mean(0), ref2)
        positions[f, idx["rod3"]] = (turn * wobble[f]).apply(local3) + centre[f]
    groups = list(idx.values())
    with caplog.at_level("WARNING"):
        skeleton = build_skeleton(positions, rec.labels, rec.rate, groups)
    names = [s.name for s in skeleton.segments]
    assert [r.getMessage() for r in caplog.records if f"joint {names[1]}-{names[2]}" in r.getMessage()
            and "deg" in r.getMessage()]
    pose = solve(skeleton, positions, rec.labels)
    k = next(i for i, j in enumerate(skeleton.joints) if {j.parent, j.child} == {names[1], names[2]})
    ends = positions[:, idx["rod2"] + idx["rod3"]]
    span = np.linalg.norm(ends[:, :, None] - ends[:, None], axis=-1).max()
    assert np.nanmax(np.linalg.norm(pose.joint_centres[:, k] - np.nanmean(ends, 1), axis=1)) < span  # not astray


def test_calibrate_and_solve_commands(tmp_path: Path) -> None:
    from mocapflow.cli import main
    from mocapflow.io.markers import MarkerData, read_markers, write_markers

    rec = _recording("rods")
    source = tmp_path / "rods.c3d"
    write_markers(source, MarkerData(positions=rec.positions[:800], labels=rec.labels, rate=rec.rate))
    skeleton_path = tmp_path / "rods.json"
    assert main(["calibrate", str(source), "-o", str(skeleton_path)]) == 0  # the default: closed-form joints
    skeleton = SkeletonModel.model_validate_json(skeleton_path.read_text())
    assert len(skeleton.segments) == 3 and len(skeleton.joints) == 2
    c3d_out = tmp_path / "solved.c3d"
    assert main(["solve", str(source), "--skeleton", str(skeleton_path), "-o", str(c3d_out)]) == 0
    solved = read_markers(c3d_out)
    assert solved.labels == rec.labels
    assert sorted(solved.extra) == sorted(j.name for j in skeleton.joints)
    seg = _true_segment(rec, skeleton)
    for joint in skeleton.joints:
        k = [frozenset(pc) for pc in zip(rec.joint_parent, rec.joint_child, strict=True)].index(
            frozenset((seg[joint.parent], seg[joint.child])))
        assert np.nanmean(np.linalg.norm(solved.extra[joint.name] - rec.joint_centres[:800, k], axis=1)) < 5.0
    json_out = tmp_path / "solved.json"
    assert main(["solve", str(source), "--skeleton", str(skeleton_path), "-o", str(json_out)]) == 0
    document = json.loads(json_out.read_text())
    assert document["joints"] == [j.name for j in skeleton.joints] and len(document["frames"]) == 800
    first = document["frames"][0]
    assert len(first["joint_centres"]) == 2 and len(first["rotations"][0]) == 4
    assert main(["solve", str(source), "--skeleton", str(tmp_path / "missing.json"), "-o", str(json_out)]) == 2


def test_calibrate_several_trials_and_a_marker_choice(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Two trials of one subject (the second with its markers in another order) give the skeleton of both at once;
    --markers/--exclude choose markers by label; an output that is an input is refused."""
    from mocapflow.cli import main
    from mocapflow.io.markers import MarkerData, write_markers

    rec = _recording("rods")
    first, second = tmp_path / "a.c3d", tmp_path / "b.trc"
    write_markers(first, MarkerData(positions=rec.positions[:700], labels=rec.labels, rate=rec.rate))
    order = list(reversed(range(len(rec.labels))))
    write_markers(second, MarkerData(positions=rec.positions[700:1400, order], labels=[rec.labels[i] for i in order],
                                     rate=rec.rate))
    both = tmp_path / "both.json"
    assert main(["calibrate", str(first), str(second), "-o", str(both)]) == 0
    assert "1400 frames of 2 trials" in capsys.readouterr().out
    skeleton = SkeletonModel.model_validate_json(both.read_text())
    assert sorted(sorted(s.markers) for s in skeleton.segments) == sorted(
        sorted(label for label, seg in zip(rec.labels, rec.marker_segment, strict=True) if seg == s)
        for s in ("rod1", "rod2", "rod3"))
    two_rods = tmp_path / "two.json"
    assert main(["calibrate", str(first), "--exclude", "rod3*", "-o", str(two_rods)]) == 0
    assert {m for s in SkeletonModel.model_validate_json(two_rods.read_text()).segments for m in s.markers} == {
        label for label in rec.labels if not label.startswith("rod3")}
    only = tmp_path / "only.json"
    assert main(["calibrate", str(first), "--markers", "rod1*", "--markers", "rod2*", "-o", str(only)]) == 0
    assert len(SkeletonModel.model_validate_json(only.read_text()).segments) == 2
    assert main(["calibrate", str(first), "--exclude", "nosuch*", "-o", str(only)]) == 2
    assert "no marker label matches 'nosuch*'" in capsys.readouterr().err
    assert main(["calibrate", str(first), "-o", str(first)]) == 2
    assert "overwrite an input" in capsys.readouterr().err
    assert first.read_bytes()[:2] != b"{"  # the recording is untouched
    assert main(["solve", str(first), "--skeleton", str(both), "-o", str(first)]) == 2


def test_solve_warns_of_a_bad_fit_naming_the_segments(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Two markers of one rod swapped in a trial: solve says the fit is poor and which segment fits worst; the
    calibrate report gives each segment's rigidity and each joint's range of motion."""
    from mocapflow.cli import main
    from mocapflow.io.markers import MarkerData, write_markers

    rec = _recording("rods")
    source, skeleton_path = tmp_path / "rods.c3d", tmp_path / "rods.json"
    write_markers(source, MarkerData(positions=rec.positions[:800], labels=rec.labels, rate=rec.rate))
    assert main(["calibrate", str(source), "-o", str(skeleton_path)]) == 0
    report = capsys.readouterr().out
    assert "rigid mm" in report and "motion deg" in report
    skeleton = SkeletonModel.model_validate_json(skeleton_path.read_text())
    assert all(s.rigidity_mm is not None and s.rigidity_mm < 2.0 for s in skeleton.segments)
    assert all(j.rotation_deg is not None and j.rotation_deg > 10.0 for j in skeleton.joints)
    assert main(["solve", str(source), "--skeleton", str(skeleton_path), "-o", str(tmp_path / "ok.json")]) == 0
    assert "warning" not in capsys.readouterr().out
    rod3 = [i for i, s in enumerate(rec.marker_segment) if s == "rod3"]
    swapped = rec.positions[:800].copy()
    swapped[:, [rod3[0], rod3[-1]]] = swapped[:, [rod3[-1], rod3[0]]]
    other = tmp_path / "swapped.c3d"
    write_markers(other, MarkerData(positions=swapped, labels=rec.labels, rate=rec.rate))
    assert main(["solve", str(other), "--skeleton", str(skeleton_path), "-o", str(tmp_path / "bad.json")]) == 0
    out = capsys.readouterr().out
    name = next(s.name for s in skeleton.segments if rec.labels[rod3[0]] in s.markers)
    assert "warning: mean marker fit" in out and f"worst fitted: {name} (" in out


def test_rigid_shape_rejects_outlier_frames_and_samples() -> None:
    rng = np.random.default_rng(8)
    local = rng.normal(size=(4, 3)) * 60
    local -= local.mean(0)
    turns = Rotation.random(500, rng=9)
    markers = np.einsum("fab,nb->fna", turns.as_matrix(), local) + rng.normal(size=(500, 3))[:, None] * 100
    markers += rng.normal(size=markers.shape) * 0.3
    markers[::20, 1] += [40.0, 0.0, 0.0]  # a marker swapped or jumping in 5 % of the frames
    markers[7, :] = np.nan
    shape = fit_shape(markers)
    aligned, _ = Rotation.align_vectors(shape.marker_offsets, local)  # the shape is in the reference frame's axes
    assert np.abs(aligned.apply(local) - shape.marker_offsets).max() < 0.2
    assert shape.frames_used < 480 and np.isnan(shape.pose.rotations[7]).all()



def test_a_shape_measures_how_far_each_marker_strays() -> None:
    """Rigid markers stray by the noise (0.5 mm per axis). A marker on soft tissue, sliding 12 mm RMS about its
    place, strays most: the fitted pose follows it a little (it is one of the four fitted), so its spread is less
    than its slide and some of it shows on the others."""
    rng = np.random.default_rng(4)
    local = rng.normal(size=(4, 3)) * 60
    local -= local.mean(0)
    turns = Rotation.random(600, rng=5).as_matrix()
    shift = rng.normal(size=(600, 3))[:, None] * 100
    noise = rng.normal(size=(600, 4, 3)) * 0.5
    rigid = fit_shape(np.einsum("fab,nb->fna", turns, local) + shift + noise).marker_spread
    assert (rigid < 1.0).all()
    slide = np.zeros((600, 4, 3))
    slide[:, 3] = rng.normal(size=(600, 3)) * 12 / np.sqrt(3)
    loose = fit_shape(np.einsum("fab,fnb->fna", turns, local + slide) + shift + noise).marker_spread
    assert 6.0 < loose[3] < 12.0 and loose[3] > 1.5 * loose[:3].max()


def _rods_with_rod3_turning(about: np.ndarray | None) -> tuple[SimRecording, np.ndarray, list[list[int]]]:
    """The rods rig with rod3 turned relative to rod2 about its true joint: by the simulated motion (``about``
    None: swings of up to 75 deg about all three axes), or only about the one axis ``about`` (40 deg sine)."""
    rec = _recording("rods")
    idx = {seg: [i for i, s in enumerate(rec.marker_segment) if s == seg] for seg in ("rod1", "rod2", "rod3")}
    positions = rec.positions.copy()
    if about is not None:
        true = rec.true_positions
        ref2 = true[0, idx["rod2"]] - true[0, idx["rod2"]].mean(0)
        centre = rec.joint_centres[:, rec.joint_child.index("rod3")]
        local3 = true[0, idx["rod3"]] - centre[0]
        turn_about = Rotation.from_rotvec(np.outer(np.sin(np.arange(len(true)) / 20), np.radians(40.0) * about))
        noise = np.random.default_rng(1).normal(0, 0.5, (len(true), 3, 3))
        for f in range(len(true)):
            turn, _ = Rotation.align_vectors(true[f, idx["rod2"]] - true[f, idx["rod2"]].mean(0), ref2)
            positions[f, idx["rod3"]] = (turn * turn_about[f]).apply(local3) + centre[f] + noise[f]
    return rec, positions, list(idx.values())


@pytest.mark.parametrize("one_axis", [False, True])
def test_a_joint_says_whether_its_trial_located_it(one_axis: bool, capsys: pytest.CaptureFixture) -> None:
    """A joint moved through a full range of motion is located within 5 mm and says so; one turned about a single
    axis is reported not located, uncertain by over 50 mm, with one line naming it and the motion it lacked, and the
    last line says what trial to add."""
    from mocapflow.commands.calibrate import summary

    rec, positions, groups = _rods_with_rod3_turning(np.array([0.0, 0.0, 1.0]) if one_axis else None)
    skeleton = build_skeleton(positions, rec.labels, rec.rate, groups, "closed-form")
    names = [s.name for s in skeleton.segments]
    joint = next(j for j in skeleton.joints if {j.parent, j.child} == {names[1], names[2]})
    assert joint.uncertainty_mm is not None
    lines = [line for line in summary(skeleton).splitlines() if line.startswith(f"joint {joint.name} not located")]
    if one_axis:
        assert joint.located is False
        assert joint.uncertainty_mm > 50
        assert len(lines) == 1 and "about one axis" in lines[0]
        assert summary(skeleton).splitlines()[-1].endswith("add a range-of-motion trial (30 deg or more of flexion "
                                                           "and abduction at each): mocapflow calibrate ROM.c3d "
                                                           "TRIAL.c3d")
        return
    assert joint.located is True and joint.uncertainty_mm < 20 and not lines
    pose = solve(skeleton, positions, rec.labels)
    k = skeleton.joints.index(joint)
    error = np.linalg.norm(pose.joint_centres[:, k] - rec.joint_centres[:, rec.joint_child.index("rod3")], axis=1)
    assert np.nanmean(error) < 5.0


def test_older_skeleton_files_still_read(tmp_path: Path) -> None:
    """A SKELETON.json written before joints said how sure they are reads with those fields unknown."""
    from mocapflow.io.skeleton import read_skeleton

    old = {"name": "old", "units": "mm", "root": "a", "segments": [
        {"name": "a", "markers": ["m1", "m2"], "marker_offsets": [[0, 0, 0], [1, 0, 0]]},
        {"name": "b", "markers": ["m3", "m4"], "marker_offsets": [[0, 0, 0], [0, 1, 0]]}],
        "joints": [{"name": "a-b", "parent": "a", "child": "b", "kind": "ball", "parent_offset": [0, 0, 1],
                    "child_offset": [0, 0, -1]}]}
    (tmp_path / "old.json").write_text(json.dumps(old))
    joint = read_skeleton(tmp_path / "old.json").joints[0]
    assert joint.located is None and joint.uncertainty_mm is None and joint.motion_sd_deg is None


@pytest.mark.integration
def test_calibrating_fragmented_labels_of_a_harsh_capture_gives_a_skeleton() -> None:
    """The offline labels of a simulated quadruped hidden a third of the time in 0.2-2 s gaps, with ghosts: some
    markers come in several fragments, and two pairs of segments are posed together in too few frames for a centre of
    rotation. Calibration gives a skeleton (such segments get no centre of rotation between them) and warns of
    nothing."""
    import math
    import warnings

    from mocapflow.mocap.evaluation import unlabel
    from mocapflow.mocap.labelling import label_sequence

    rec = simulate(SimulatorConfig(rig="quadruped", rate=120, noise_mm=0.5, seed=7), 1500)
    points, _ = unlabel(rec.positions, 120, seed=2, gaps_per_s=math.log(1.5) / 1.1, long_fraction=1.0,
                        long_s=(0.2, 2.0), ghosts=0.2, ghost_frames=1)
    tracks, labels = label_sequence(points, 120)
    assert len(labels) > len(rec.labels)  # fragments: 40 tracks of 37 markers
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        skeleton = calibrate(tracks, labels, 120)
    assert len(skeleton.segments) >= 10 and len(skeleton.joints) == len(skeleton.segments) - 1
