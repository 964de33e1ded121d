"""Rotors, segment poses and closed-form centres of rotation against exactly known motion."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocapflow.mocap.cor import SequentialCoR, joint_track
from mocapflow.mocap.rigidfit import CLOSED_FORM_GAP, fit_pose, kabsch, quaternion_matrices, rotor


def _two_segments(frames: int = 600, hinge: bool = False, noise: float = 0.5, seed: int = 0) -> dict:
    """A parent and a child segment (4 markers each) joined at a known point, in random motion."""
    rng = np.random.default_rng(seed)
    parent_local = rng.normal(size=(4, 3)) * 60
    child_local = rng.normal(size=(4, 3)) * 60
    parent_joint = np.array([10.0, -20.0, -180.0])  # joint in the parent frame
    child_joint = np.array([-5.0, 15.0, 160.0])  # joint in the child frame
    rp = Rotation.from_rotvec(rng.normal(size=(frames, 3)) * 0.8)
    if hinge:
        relative = Rotation.from_rotvec(np.outer(rng.uniform(0.0, 2.0, frames), [0.0, 1.0, 0.0]))
    else:
        relative = Rotation.from_rotvec(rng.normal(size=(frames, 3)) * 0.5)
    rc = rp * relative
    tp = rng.normal(size=(frames, 3)) * 300
    centre = rp.apply(parent_joint) + tp
    tc = centre - rc.apply(child_joint)
    pm = np.einsum("fab,nb->fna", rp.as_matrix(), parent_local) + tp[:, None]
    cm = np.einsum("fab,nb->fna", rc.as_matrix(), child_local) + tc[:, None]
    pm += rng.normal(size=pm.shape) * noise
    cm += rng.normal(size=cm.shape) * noise
    return dict(parent_local=parent_local, child_local=child_local, parent_joint=parent_joint,
                child_joint=child_joint, rp=rp, rc=rc, tp=tp, tc=tc, centre=centre, pm=pm, cm=cm)


def test_rotor_matches_scipy_align_vectors_frame_by_frame() -> None:
    rng = np.random.default_rng(1)
    x = rng.normal(size=(50, 5, 3)) * 100
    truth = Rotation.random(50, rng=2)
    y = np.einsum("fab,fnb->fna", truth.as_matrix(), x) + rng.normal(size=x.shape)
    quats, gap = rotor(x, y)
    for f in range(50):
        expected, _ = Rotation.align_vectors(y[f], x[f])
        assert (Rotation.from_quat(quats[f]) * expected.inv()).magnitude() < 1e-9
    assert (gap > 0.05).all()


def test_kabsch_matches_scipy_align_vectors_on_weighted_flat_and_mirrored_sets() -> None:
    """The centroid fit (Horn's rotation of the cross-covariance) is scipy's least-squares rotation, whatever the
    weights, for nearly flat point sets, and for mirror images (the best proper rotation, never the reflection); and it
    says so where the points fix no rotation."""
    rng = np.random.default_rng(4)
    for k in range(300):
        m = int(rng.integers(3, 8))
        local = rng.normal(size=(m, 3)) * rng.uniform(1.0, 300.0)
        if k % 5 == 0:
            local[:, 2] *= 1e-3  # nearly flat
        weight = rng.uniform(0.1, 1.0, m)
        world = Rotation.random(rng=k).apply(local) + rng.normal(size=(m, 3)) * rng.uniform(0.0, 5.0) + 500.0
        if k % 7 == 0:
            world = -world  # a mirror image
        r, t, ok = kabsch(local[None], world[None], weight[None])
        centred = [x - np.average(x, axis=0, weights=weight) for x in (local, world)]
        expected, _ = Rotation.align_vectors(centred[1], centred[0], weights=weight)
        assert ok[0]
        np.testing.assert_allclose(r[0], expected.as_matrix(), atol=1e-9)
        np.testing.assert_allclose(np.average(local, axis=0, weights=weight) @ r[0].T + t[0],
                                   np.average(world, axis=0, weights=weight), atol=1e-6)  # centroid on centroid
    line = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    assert not kabsch(line[None], line[None] + 5.0, np.ones((1, 3)))[2][0]  # collinear points fix no rotation


def test_rotor_is_horns_eigenvector_at_every_gap_closed_form_or_iterated() -> None:
    """Horn's rotation is the top eigenvector of his 4x4 matrix N. Where the top two eigenvalues stand clear of each
    other it is found in closed form, elsewhere by Jacobi's method: both agree with a general eigen-solver on sets
    from flat, nearly collinear and mirrored to well spread, and the gap they report is the eigenvalues' own."""
    rng = np.random.default_rng(8)
    gaps = []
    for k in range(400):
        m = int(rng.integers(3, 7))
        x = rng.normal(size=(m, 3)) * rng.uniform(1.0, 300.0)
        x[:, 1:] *= rng.choice([1.0, 0.3, 1e-2, 1e-4])[None] * np.array([1.0, rng.uniform(0.0, 1.0)])  # thin sets
        y = Rotation.random(rng=k).apply(x) + rng.normal(size=x.shape) * rng.uniform(0.0, 2.0)
        if k % 5 == 0:
            y = -y
        x, y = x - x.mean(0), y - y.mean(0)
        (xx, xy, xz), (yx, yy, yz), (zx, zy, zz) = x.T @ y
        n = np.array([[xx + yy + zz, yz - zy, zx - xz, xy - yx], [yz - zy, xx - yy - zz, xy + yx, zx + xz],
                      [zx - xz, xy + yx, -xx + yy - zz, yz + zy], [xy - yx, zx + xz, yz + zy, -xx - yy + zz]])
        values, vectors = np.linalg.eigh(n)
        quat, gap = rotor(x, y)
        expected_gap = (values[3] - values[2]) / np.abs(values).max()
        assert gap == pytest.approx(expected_gap, abs=1e-9)
        gaps.append(gap)
        if expected_gap > 1e-6:  # a single rotation: the eigenvector, up to its sign
            top = vectors[[1, 2, 3, 0], 3]
            assert quat[3] >= 0
            np.testing.assert_allclose(quat, top * np.sign(top[3]), atol=1e-9 / expected_gap)
    assert min(gaps) < CLOSED_FORM_GAP < max(gaps)  # both ways taken


def test_rotor_ignores_missing_rows_and_flags_two_point_sets() -> None:
    rng = np.random.default_rng(3)
    x = rng.normal(size=(4, 3)) * 100
    truth = Rotation.random(rng=4)
    y = truth.apply(x)
    y[1] = np.nan
    quats, _ = rotor(x, y)
    assert (Rotation.from_quat(quats) * truth.inv()).magnitude() < 1e-9
    _, gap_one_vector = rotor(x[:1], y[:1])
    assert gap_one_vector < 1e-9  # a single vector leaves the turn about itself free


def test_fit_pose_recovers_poses_with_gaps_and_keeps_a_pivot_fixed() -> None:
    s = _two_segments(noise=0.0)
    observed = s["pm"].copy()
    observed[::3, 0] = np.nan
    observed[1::3, 2] = np.nan
    fit = fit_pose(s["parent_local"], observed)
    assert fit.determined.all()
    assert (Rotation.from_quat(fit.rotations) * s["rp"].inv()).magnitude().max() < 1e-9
    assert np.abs(fit.translations - s["tp"]).max() < 1e-6
    two = s["cm"][:, :2]  # one marker and the joint: rotation about the joint fixed by two vectors
    pivot = fit_pose(s["child_local"][:2], two, s["child_joint"], s["centre"])
    assert pivot.determined.all()
    placed = np.einsum("fab,b->fa", pivot.rotation_matrices, s["child_joint"]) + pivot.translations
    assert np.abs(placed - s["centre"]).max() < 1e-6
    assert (Rotation.from_quat(pivot.rotations) * s["rc"].inv()).magnitude().max() < 1e-9


def test_fit_pose_marks_underdetermined_frames() -> None:
    s = _two_segments(frames=20, noise=0.0)
    observed = s["pm"].copy()
    observed[:10, 2:] = np.nan  # two markers: the turn about their line is free
    observed[15:, 1:] = np.nan  # one marker: no pose at all
    fit = fit_pose(s["parent_local"], observed)
    assert not fit.determined[:10].any() and fit.determined[10:15].all()
    assert np.isnan(fit.rotations[15:]).all() and np.isnan(fit.residual[15:]).all()


def test_sequential_cor_finds_a_ball_joint() -> None:
    s = _two_segments()
    cor = SequentialCoR(s["parent_local"], s["child_local"])
    cor.update_markers(s["pm"], s["cm"])
    est = cor.estimate()
    assert np.linalg.norm(est.parent_offset - s["parent_joint"]) < 1.0
    assert np.linalg.norm(est.child_offset - s["child_joint"]) < 1.0
    assert not est.is_hinge
    parent_offset, child_offset, residual = est
    assert residual == est.residual < 3.0 and parent_offset is est.parent_offset and child_offset is est.child_offset


def test_sequential_updates_equal_the_batch_and_cost_the_same_per_frame() -> None:
    s = _two_segments(frames=200, noise=0.3)
    rp, rc = s["rp"].as_matrix(), s["rc"].as_matrix()
    batch = SequentialCoR()
    batch.update(rp, s["tp"], rc, s["tc"])
    sequential = SequentialCoR()
    for f in range(200):
        sequential.update(rp[f], s["tp"][f], rc[f], s["tc"][f])
    a, b = batch.estimate(), sequential.estimate()
    assert np.allclose(a.parent_offset, b.parent_offset) and np.allclose(a.child_offset, b.child_offset)
    assert np.allclose(a.parent_offset, s["parent_joint"], atol=1e-6)  # exact poses: exact centre
    assert a.residual < 1e-6
    with pytest.raises(ValueError):
        SequentialCoR().estimate()


def test_sequential_cor_detects_a_hinge_and_picks_the_minimum_norm_point_on_its_axis() -> None:
    s = _two_segments(hinge=True)
    cor = SequentialCoR(s["parent_local"], s["child_local"])
    cor.update_markers(s["pm"], s["cm"])
    est = cor.estimate()
    axis = np.array([0.0, 1.0, 0.0])
    assert est.is_hinge
    assert abs(abs(est.axis @ axis) - 1) < 1e-3 and abs(abs(est.child_axis @ axis) - 1) < 1e-3
    off_axis = est.parent_offset - s["parent_joint"]
    assert np.linalg.norm(off_axis - (off_axis @ axis) * axis) < 1.0  # on the true axis
    # the point on the axis nearest both segment origins: equal and opposite axial coordinates
    assert abs(est.parent_offset @ axis + est.child_offset @ axis) < 1.0


def test_a_near_hinge_with_skin_artefact_is_located_along_its_axis_only_within_its_axial_uncertainty() -> None:
    # a knee: flexion plus +-0.1 rad of other rotations, and a 5 mm artefact of the child's cluster that follows the
    # joint angles (as soft tissue does); exact poses otherwise
    rng = np.random.default_rng(11)
    frames = 800
    t = np.arange(frames) / 100
    parent_joint, child_joint = np.array([10.0, -20.0, -180.0]), np.array([-5.0, 15.0, 160.0])
    rp = Rotation.from_rotvec(rng.normal(size=(frames, 3)) * 0.8)
    angles = np.column_stack([0.1 * np.sin(2.3 * t), 0.6 + 0.6 * np.sin(t), 0.1 * np.sin(3.1 * t + 1)])
    rc = rp * Rotation.from_rotvec(angles)
    tp = rng.normal(size=(frames, 3)) * 300
    tc = rp.apply(parent_joint) + tp - rc.apply(child_joint)
    tc += rc.apply(5.0 * np.column_stack([np.sin(2.3 * t), np.cos(t), np.sin(3.1 * t + 1)]))
    cor = SequentialCoR()
    cor.update(rp.as_matrix(), tp, rc.as_matrix(), tc)
    est = cor.estimate()
    assert not est.is_hinge and abs(abs(est.axis[1]) - 1) < 0.01  # not an exact hinge; its axis is the flexion's
    along = abs((est.parent_offset - parent_joint) @ est.axis)
    across = np.linalg.norm(est.parent_offset - parent_joint - (est.parent_offset - parent_joint) @ est.axis * est.axis)
    assert along > 10.0 > across  # the artefact moves the centre along the axis, hardly across it
    assert along < est.axial_uncertainty
    # the leverage is what moving the centre along the axis (the parent's side refitted) adds to the mean misfit
    shift = 20.0
    q = est.child_offset + shift * est.child_axis
    rpm, rcm = rp.as_matrix(), rc.as_matrix()
    p = np.einsum("fba,fb->fa", rpm, np.einsum("fab,b->fa", rcm, q) + tc - tp).mean(0)
    misfit = np.einsum("fab,b->fa", rpm, p) + tp - np.einsum("fab,b->fa", rcm, q) - tc
    assert np.isclose((misfit ** 2).sum(1).mean(), est.residual ** 2 + est.leverage * shift ** 2, rtol=1e-6)


def test_joint_track_uses_the_visible_side_during_occlusions() -> None:
    s = _two_segments(frames=50, noise=0.0)
    rp, rc = s["rp"].as_matrix(), s["rc"].as_matrix()
    rp[:10] = np.nan
    rc[40:] = np.nan
    track = joint_track(rp, s["tp"], rc, s["tc"], s["parent_joint"], s["child_joint"])
    assert np.abs(track - s["centre"]).max() < 1e-6
    both_missing = joint_track(rp[:1], s["tp"][:1], np.full((1, 3, 3), np.nan), s["tc"][:1], s["parent_joint"],
                               s["child_joint"])
    assert np.isnan(both_missing).all()
    assert np.isnan(quaternion_matrices(np.full((2, 4), np.nan))).all()


def test_rotor_weights_match_scipy() -> None:
    rng = np.random.default_rng(6)
    x = rng.normal(size=(6, 3)) * 100
    y = Rotation.random(rng=7).apply(x) + rng.normal(size=(6, 3)) * 5
    w = rng.uniform(0.1, 2.0, 6)
    quats, _ = rotor(x, y, w)
    expected, _ = Rotation.align_vectors(y, x, weights=w)
    assert (Rotation.from_quat(quats) * expected.inv()).magnitude() < 1e-9


def test_hold_keeps_the_orientation_through_two_marker_stretches() -> None:
    frames = 60
    local = np.array([[100.0, 0, 0], [-100.0, 0, 0], [0, 80.0, 0], [0, 0, 90.0]])
    truth = Rotation.from_rotvec(np.outer(np.linspace(0, 0.6, frames), [0.2, 1.0, 0.3]))
    observed = np.einsum("fab,nb->fna", truth.as_matrix(), local) + 50.0
    observed[:5, 2:] = np.nan  # a leading stretch and a middle one with two markers only
    observed[30:45, 2:] = np.nan
    held = fit_pose(local, observed, hold=True)
    assert not held.determined[30:45].any()
    error = np.degrees((Rotation.from_quat(held.rotations) * truth.inv()).magnitude())
    assert error.max() < 3.0  # the turn about the marker line is carried from the neighbouring frames
    assert np.nanmax(held.residual) < 1e-6  # and the visible markers still fit exactly
