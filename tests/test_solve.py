"""The compiled pose solver: built anew it gives what a fresh solve gives, kept frame after frame it holds a segment
seen in one direction from its earlier calls, the batched rigid fit it rests on gives each segment exactly its own
fit, and quaternion matrices are scipy's bit for bit."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocapflow.mocap.model import SkeletonModel
from mocapflow.mocap.rigidfit import fit_pose, quaternion_matrices
from mocapflow.mocap.rigs import make_rig
from mocapflow.mocap.simulator import SimRecording, SimulatorConfig, simulate, truth_skeleton
from mocapflow.mocap.solve import PoseSolver, SkeletonPose, solve


@cache
def _case() -> tuple[SimRecording, SkeletonModel]:
    rec = simulate(SimulatorConfig(rate=120, seed=3, noise_mm=1.0, dropout_rate=4.0, long_gaps=20.0), 40)
    return rec, truth_skeleton(make_rig("human"), rec.true_positions[0])


def _same(a: SkeletonPose, b: SkeletonPose) -> None:
    for field in ("rotations", "translations", "joint_centres", "residual"):
        np.testing.assert_array_equal(np.isnan(getattr(a, field)), np.isnan(getattr(b, field)))
        np.testing.assert_allclose(getattr(a, field), getattr(b, field), rtol=0, atol=1e-12, equal_nan=True)
    assert a.marker_fit == pytest.approx(b.marker_fit, abs=1e-12)


def test_a_solver_gives_what_a_fresh_solve_gives_frame_by_frame_and_in_batches() -> None:
    rec, skeleton = _case()
    assert np.isnan(rec.positions).any()  # gaps, so that some segments are short of markers
    labels = rec.labels[::-1]  # the solver follows the label order it was built for
    positions = rec.positions[:, ::-1]
    for f in range(0, 40, 7):
        _same(PoseSolver(skeleton, labels)(positions[f:f + 1]), solve(skeleton, positions[f:f + 1], labels))
    _same(PoseSolver(skeleton, labels)(positions[:20]), solve(skeleton, positions[:20], labels))
    whole = PoseSolver(skeleton, labels)(positions)
    assert whole.rotations.shape == (40, len(skeleton.segments), 4)
    assert np.isfinite(whole.joint_centres).all()


def test_a_kept_solver_holds_a_segment_seen_in_one_direction_from_where_an_earlier_call_left_it() -> None:
    """The right hand shows one marker from frame 10 on: with its wrist that fixes one direction only. Solved one
    frame per call, as live, it holds from the last frame that fixed it, exactly as one solve of every frame does;
    without that memory its turn about the marker would be arbitrary, and chaotic."""
    rec, skeleton = _case()
    labels = rec.labels
    positions = np.array(rec.true_positions)
    positions[10:, [labels.index(m) for m in ("RHN2", "RHN3")]] = np.nan
    hand = [s.name for s in skeleton.segments].index("right_hand")

    def live(shift: float) -> np.ndarray:
        solver = PoseSolver(skeleton, labels)
        return np.concatenate([solver(positions[f:f + 1] + shift).rotations for f in range(40)])

    kept, whole = live(0.0), solve(skeleton, positions, labels)
    np.testing.assert_allclose(kept, whole.rotations, rtol=0, atol=1e-12)
    assert np.isfinite(kept[10:, hand]).all()
    # an upstream change of a nanometre moves the held hand by as little
    np.testing.assert_allclose(live(1e-6), kept, rtol=0, atol=1e-6)


def test_a_segment_no_frame_fixes_turns_with_its_parent_then_points_at_its_marker() -> None:
    """The right hand shows one marker in every frame: with its wrist that fixes one direction only, and no frame
    fixes more. Each frame it turns as the forearm does, then by the smallest turn that points it at its marker, so
    its turn about that marker follows the forearm instead of coming out arbitrary, and chaotic."""
    rec, skeleton = _case()
    labels = rec.labels
    positions = np.array(rec.true_positions)
    positions[:, [labels.index(m) for m in ("RHN2", "RHN3")]] = np.nan
    names = [s.name for s in skeleton.segments]
    hand, forearm = names.index("right_hand"), names.index("right_forearm")
    wrist = next(j for j in skeleton.joints if j.child == "right_hand")
    pose = solve(skeleton, positions, labels)
    hand_rot = Rotation.from_quat(pose.rotations[:, hand])
    turn = hand_rot * Rotation.from_quat(pose.rotations[:, forearm]).inv()
    local = np.asarray(skeleton.segments[hand].marker_offsets)[0] - np.asarray(wrist.child_offset)
    seen = positions[:, labels.index("RHN1")] - pose.joint_centres[:, skeleton.joints.index(wrist)]
    carried = Rotation.from_quat(pose.rotations[:, forearm]).apply(local)
    np.testing.assert_allclose(hand_rot.apply(local) / np.linalg.norm(local),
                               seen / np.linalg.norm(seen, axis=1, keepdims=True), atol=1e-9)
    between = np.arccos(np.clip((carried * seen).sum(1) / np.linalg.norm(carried, axis=1)
                                / np.linalg.norm(seen, axis=1), -1, 1))
    np.testing.assert_allclose(turn.magnitude(), between, atol=1e-7)
    shifted = solve(skeleton, positions + 1e-6, labels)
    np.testing.assert_allclose(shifted.rotations[:, hand], pose.rotations[:, hand], rtol=0, atol=1e-6)


def test_markers_missing_from_the_labels_count_as_never_seen() -> None:
    rec, skeleton = _case()
    keep = [i for i, label in enumerate(rec.labels) if label not in skeleton.segments[-1].markers]
    pose = PoseSolver(skeleton, [rec.labels[i] for i in keep])(rec.positions[:3, keep])
    hidden = np.array(rec.positions[:3])
    hidden[:, [rec.labels.index(m) for m in skeleton.segments[-1].markers]] = np.nan
    _same(pose, solve(skeleton, hidden, rec.labels))


def test_an_uncalibrated_skeleton_is_refused_when_the_solver_is_built() -> None:
    _, skeleton = _case()
    bare = skeleton.model_copy(deep=True)
    bare.segments[2].marker_offsets = None
    with pytest.raises(ValueError, match="no marker offsets"):
        PoseSolver(bare, ["a"])


def test_a_batch_of_segments_fits_each_exactly_as_alone() -> None:
    rng = np.random.default_rng(0)
    sizes, frames = (2, 5, 3, 9), 30
    local = [rng.normal(0, 80, (n, 3)) for n in sizes]
    turn = Rotation.random(frames * len(sizes), random_state=1).as_matrix().reshape(frames, len(sizes), 3, 3)
    observed = [np.einsum("fab,nb->fna", turn[:, s], x) + rng.normal(0, 500, 3) for s, x in enumerate(local)]
    for obs in observed:
        obs[rng.random(obs.shape[:2]) < 0.4] = np.nan
    pivot_local = rng.normal(0, 50, (len(sizes), 3))
    pivot_world = rng.normal(0, 500, (frames, len(sizes), 3))
    pivot_world[rng.random((frames, len(sizes))) < 0.3] = np.nan
    width = max(sizes)
    batch_local, batch_observed = np.zeros((len(sizes), width, 3)), np.full((frames, len(sizes), width, 3), np.nan)
    for s, n in enumerate(sizes):
        batch_local[s, :n], batch_observed[:, s, :n] = local[s], observed[s]
    for pivots in ((None, None), (pivot_local, pivot_world)):
        batch = fit_pose(batch_local, batch_observed, *pivots, hold=True)
        for s in range(len(sizes)):
            alone = fit_pose(local[s], observed[s], *(None if p is None else p[..., s, :] for p in pivots), hold=True)
            np.testing.assert_array_equal(batch.rotations[:, s], alone.rotations)
            np.testing.assert_array_equal(batch.translations[:, s], alone.translations)
            np.testing.assert_array_equal(batch.determined[:, s], alone.determined)
        assert (~batch.determined & np.isfinite(batch.rotations).all(-1)).any()  # some frames were held


def test_quaternion_matrices_are_scipys_bit_for_bit() -> None:
    q = np.random.default_rng(2).normal(size=(500, 3, 4)) * 3
    q[4, 1] = np.nan
    known = np.isfinite(q).all(-1)
    expected = np.full((500, 3, 3, 3), np.nan)
    expected[known] = Rotation.from_quat(q[known]).as_matrix()
    np.testing.assert_array_equal(quaternion_matrices(q), expected)
    with pytest.raises(ValueError, match="zero norm"):
        quaternion_matrices(np.zeros(4))
