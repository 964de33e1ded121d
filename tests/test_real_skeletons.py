"""Skeletons of every real full-body recording, calibrated with no option, checked against anatomy.

The marker-name -> body-region maps and the checks live in benchmarks/real_skeletons.py (which prints the same table
for the docs); calibration never sees them.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from real_skeletons import FILES, check, region  # noqa: E402

from mocapflow.io.markers import read_markers  # noqa: E402
from mocapflow.mocap.calibration import calibrate  # noqa: E402
from mocapflow.mocap.rigs import make_rig  # noqa: E402
from mocapflow.mocap.simulator import SimRecording, SimulatorConfig, forward_kinematics, simulate  # noqa: E402
from mocapflow.mocap.solve import solve  # noqa: E402


@pytest.mark.integration
@pytest.mark.parametrize("name", FILES)
def test_real_recording_gives_an_anatomical_skeleton(name: str, real_file: Callable[[str], Path]) -> None:
    data = read_markers(real_file(name))
    skeleton = calibrate(data.positions, data.labels, data.rate)
    checks = check(skeleton, data.positions, data.labels)
    assert not checks.mixed, f"segments mixing limbs, or a leg and the trunk: {checks.mixed}"
    assert not checks.not_chains, f"limbs that are not one chain hanging from the body: {checks.not_chains}"
    assert not checks.short_legs, f"legs without thigh, shank and foot: {checks.short_legs}"
    assert checks.fit_mm < 10.0
    used = {m for s in skeleton.segments for m in s.markers}
    assert len(used) >= 0.9 * len(data.labels)  # markers are left out only one by one, with a reason


@pytest.mark.integration
def test_a_short_trial_keeps_the_back_markers_off_the_legs(real_file: Callable[[str], Path]) -> None:
    """cmu_85_02's first 405 frames, in which a thigh marker and a back marker 687 mm away happened to keep still
    together: no segment holds both a leg and the trunk."""
    data = read_markers(real_file("cmu_85_02.c3d"))
    half = data.positions[: len(data.positions) // 2]
    checks = check(calibrate(half, data.labels, data.rate), half, data.labels)
    assert not checks.mixed, f"segments mixing limbs, or a leg and the trunk: {checks.mixed}"


@pytest.mark.integration
def test_a_short_running_trial_hangs_each_shank_from_its_own_thigh(real_file: Callable[[str], Path]) -> None:
    """The running trial's first 1.16 s: its left thigh keeps two markers (the third moved with the pelvis), so the tree
    is built from the closest markers' spreads, which over a stride kept the right shank's as still to a pelvis marker
    and the left shank's to the right thigh's as to their own knees. Their centres of rotation lie 109 and 131 mm
    apart as each segment places them: no joint."""
    data = read_markers(real_file("hamner_run200.trc"))
    half = data.positions[: len(data.positions) // 2]
    skeleton = calibrate(half, data.labels, data.rate)
    checks = check(skeleton, half, data.labels)
    segment = {m: s.name for s in skeleton.segments for m in s.markers}
    joined = {frozenset((j.parent, j.child)) for j in skeleton.joints}
    assert frozenset((segment["RTB1"], segment["RTH1"])) in joined, [j.name for j in skeleton.joints]
    assert frozenset((segment["LTB1"], segment["LTH2"])) in joined, [j.name for j in skeleton.joints]
    assert "right leg" not in checks.not_chains
    assert checks.fit_mm < 5.0


def test_region_map_knows_each_file(real_file: Callable[[str], Path]) -> None:
    """The checks mean something only if every limb of each full-body file is mapped."""
    for name in FILES:
        labels = read_markers(real_file(name)).labels
        regions = {region(label) for label in labels}
        limbs = {"left leg", "right leg"} | ({"left arm", "right arm"} if "lowerbody" not in name else set())
        assert limbs <= regions, name


def _kabsch(reference: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame rotation (F, 3, 3) and translation (F, 3) taking ``reference`` (n, 3) onto ``points`` (F, n, 3)."""
    a = reference - reference.mean(0)
    b = points - points.mean(1, keepdims=True)
    u, _, vt = np.linalg.svd(np.einsum("fni,nj->fij", b, a))
    d = np.sign(np.linalg.det(u @ vt))
    rot = u @ (np.eye(3)[None] * np.stack([np.ones_like(d), np.ones_like(d), d], 1)[:, None]) @ vt
    return rot, points.mean(1) - np.einsum("fij,j->fi", rot, reference.mean(0))


def _cmu_like(seed: int = 3, hidden: float = 0.2) -> tuple[np.ndarray, list[str], dict[str, str], SimRecording]:
    """The simulated human wearing a CMU-like set: two markers per limb segment, one of them on the distal joint
    (knee, ankle, elbow, wrist: rigid with the proximal segment, 40 mm off the centre), feet of three, hands of two;
    1 mm noise and a fifth of every marker's time hidden in 0.2-1 s gaps. Returns positions, labels, the true
    segment of each label, and the recording."""
    rec = simulate(SimulatorConfig(rig="human", rate=120, noise_mm=0.0, seed=seed), 2400)
    true = rec.true_positions
    column = {label: i for i, label in enumerate(rec.labels)}
    chosen = {"pelvis": ["LASI", "RASI", "LPSI", "RPSI"], "torso": ["C7", "CLAV", "STRN", "RBAK"],
              "head": ["LFHD", "RFHD", "LBHD", "RBHD"]}
    joint_marker = {"thigh": ("KNE", "knee"), "shank": ("ANK", "ankle"), "upper_arm": ("ELB", "elbow"),
                    "forearm": ("WRA", "wrist")}
    own = {"thigh": "TH1", "shank": "SH1", "upper_arm": "UA1", "forearm": "FA1"}
    columns = [true[:, [column[m] for m in ms]] for ms in chosen.values()]
    labels = [m for ms in chosen.values() for m in ms]
    segment_of = {m: seg for seg, ms in chosen.items() for m in ms}
    for side, word in (("L", "left"), ("R", "right")):
        for part, (suffix, joint) in joint_marker.items():
            segment = f"{word}_{part}"
            cluster = [i for i, s in enumerate(rec.marker_segment) if s == segment]
            rot, shift = _kabsch(true[0, cluster], true[:, cluster])
            centre = rec.joint_centres[:, rec.joint_names.index(f"{word}_{joint}")]
            offset = np.einsum("ji,j->i", rot[0], [0.0, 40.0 if side == "L" else -40.0, 0.0])  # lateral at rest
            marker = centre + np.einsum("fij,j->fi", rot, offset)
            columns += [true[:, [column[side + own[part]]]], marker[:, None]]
            labels += [side + own[part], side + suffix]
            segment_of.update({side + own[part]: segment, side + suffix: segment})
        for part, names in (("foot", ["HEE", "TOE", "MT5"]), ("hand", ["HN1", "HN2"])):
            columns.append(true[:, [column[side + n] for n in names]])
            labels += [side + n for n in names]
            segment_of.update({side + n: f"{word}_{part}" for n in names})
    positions = np.concatenate(columns, axis=1)
    rng = np.random.default_rng(seed)
    positions = positions + rng.normal(0.0, 1.0, positions.shape)
    for m in range(positions.shape[1]):
        while np.isnan(positions[:, m, 0]).mean() < hidden:
            start, length = rng.integers(0, len(positions)), rng.integers(24, 120)
            positions[start:start + length, m] = np.nan
    return positions, labels, segment_of, rec


@pytest.mark.integration
def test_simulated_markers_on_joints_two_per_segment_and_occluded() -> None:
    """The hard case of real marker sets, where the truth is known: segments, tree and joint centres."""
    positions, labels, segment_of, rec = _cmu_like()
    skeleton = calibrate(positions, labels, rec.rate)
    truth = sorted(sorted(m for m in labels if segment_of[m] == s) for s in set(segment_of.values()))
    assert sorted(sorted(s.markers) for s in skeleton.segments) == truth
    seg = {s.name: segment_of[s.markers[0]] for s in skeleton.segments}
    true_joints = {frozenset(pc): k for k, pc in enumerate(zip(rec.joint_parent, rec.joint_child, strict=True))}
    found = {frozenset((seg[j.parent], seg[j.child])) for j in skeleton.joints}
    assert found == set(true_joints)
    pose = solve(skeleton, positions, labels)
    errors = {}
    for k, j in enumerate(skeleton.joints):
        t = true_joints[frozenset((seg[j.parent], seg[j.child]))]
        errors[rec.joint_names[t]] = np.linalg.norm(pose.joint_centres[:, k] - rec.joint_centres[:, t], axis=1)
    typical = {name: float(np.nanmedian(e)) for name, e in errors.items()}
    assert max(typical.values()) < 5.0, typical  # hinges placed on their axis, not between the markers
    assert np.nanmean(np.concatenate(list(errors.values()))) < 10.0
    assert pose.marker_fit < 5.0  # 1 mm noise; frames with a whole two-marker segment hidden cost the rest


def _squats(frames: int = 1200, rate: float = 120.0, seed: int = 5) -> tuple[np.ndarray, list[str], list[str]]:
    """The simulated human squatting: both legs bend together (hips, knees and ankles in step, with a few degrees of
    unequal abduction, as people squat), the trunk leans with them, the arms are held still against the trunk;
    1 mm noise. Returns positions, labels and each marker's segment."""
    rig = make_rig("human")
    t = np.arange(frames) / rate
    depth = np.radians(50.0) * (1 - np.cos(2 * np.pi * t / 3.0)) / 2  # 0 to 50 degrees every 3 s
    rotvec = np.zeros((frames, len(rig.segments), 3))
    for side, sign, wobble in (("left", 1.0, 0.7), ("right", -1.0, 0.9)):
        s = {name: rig.segments.index(f"{side}_{name}") for name in ("thigh", "shank", "foot")}
        rotvec[:, s["thigh"], 1] = -depth
        rotvec[:, s["thigh"], 0] = sign * np.radians(2.0) * np.sin(wobble * 2 * np.pi * t)
        rotvec[:, s["shank"], 1] = 2 * depth
        rotvec[:, s["foot"], 1] = -depth
    rotvec[:, rig.segments.index("torso"), 1] = 0.6 * depth
    root = np.stack([-120 * np.sin(depth), np.zeros(frames), 950 - 430 * (1 - np.cos(depth)) * 2], 1)
    rot, pos = forward_kinematics(rig, Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(
        frames, -1, 3, 3), root)
    markers = np.einsum("fnij,nj->fni", rot[:, rig.marker_segment], rig.marker_offsets) + pos[:, rig.marker_segment]
    markers += np.random.default_rng(seed).normal(0.0, 1.0, markers.shape)
    return markers, list(rig.marker_labels), [rig.segments[s] for s in rig.marker_segment]


def test_symmetric_squats_keep_left_and_right_legs_apart() -> None:
    """Both legs moving together keep their mutual distances almost as a rigid body would: only the few degrees by
    which people squat unevenly, far above the noise, tell them apart. Arms held still stay with the trunk, which is
    what the data say."""
    positions, labels, segment_of = _squats()
    skeleton = calibrate(positions, labels, 120.0)
    side = {m: "left" if s.startswith("left") else "right" if s.startswith("right") else "" for m, s in
            zip(labels, segment_of, strict=True)}
    leg = {m: any(part in s for part in ("thigh", "shank", "foot")) for m, s in zip(labels, segment_of, strict=True)}
    for s in skeleton.segments:
        sides = {side[m] for m in s.markers if leg[m]}
        assert len(sides) <= 1, s.markers  # no segment holds both legs
        assert all(leg[m] for m in s.markers) or not any(leg[m] for m in s.markers), s.markers  # nor leg and trunk
    for word in ("left", "right"):
        legs = {segment_of[labels.index(m)] for s in skeleton.segments for m in s.markers
                if leg[m] and side[m] == word and all(leg[x] for x in s.markers)}
        truth = {f"{word}_thigh", f"{word}_shank", f"{word}_foot"}
        assert legs == truth
        found = {frozenset(segment_of[labels.index(m)] for m in s.markers) for s in skeleton.segments}
        assert {frozenset({t}) for t in truth} <= found  # thigh, shank and foot exactly
    assert solve(skeleton, positions, labels).marker_fit < 3.0
