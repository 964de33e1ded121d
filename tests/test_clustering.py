"""Markers to segments: simulated rigs against their true partition, the real lower-body file against its expert
segmentation, and the streaming tracker against the batch statistics."""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
import pytest

from mocapflow.mocap.clustering import (
    PairStatistics,
    SegmentTracker,
    cluster_distance_threshold,
    cluster_spectral,
    distance_spread,
    eigengap_k,
    partition_rigidity,
    partition_spectral,
    segment_names,
    spectral_embedding,
)
from mocapflow.mocap.simulator import SimRecording, SimulatorConfig, simulate


@cache
def _recording(rig: str, frames: int = 1200) -> SimRecording:
    return simulate(SimulatorConfig(rig=rig, rate=120, noise_mm=0.5, seed=3), frames)


def _truth(rec: SimRecording) -> list[list[int]]:
    segments = dict.fromkeys(rec.marker_segment)
    return sorted(sorted(i for i, s in enumerate(rec.marker_segment) if s == seg) for seg in segments)


def test_distance_spread_matches_the_direct_standard_deviation_with_gaps() -> None:
    rng = np.random.default_rng(0)
    positions = rng.normal(size=(700, 5, 3)) * 50 + 1000
    positions[rng.random((700, 5)) < 0.2] = np.nan
    d = np.linalg.norm(positions[:, :, None] - positions[:, None], axis=-1)
    expected = np.nanstd(d, axis=0)
    # chunks of a few frames: the running sums must add up
    got = distance_spread(positions, values=128 * 6, clip=np.inf)
    assert np.allclose(got, expected, atol=1e-9)


def test_a_few_wrong_samples_do_not_make_a_rigid_pair_look_loose() -> None:
    """A ghost taken for a marker in one frame of 3000, 120 mm off: without it the pair's spread is its noise."""
    rng = np.random.default_rng(1)
    frames = 3000
    centre = np.cumsum(rng.normal(0, 5, (frames, 3)), axis=0)
    positions = np.stack([centre, centre + [30.0, 0, 0], centre + [0, 500.0, 0]], axis=1)
    positions[:, 2] += np.cumsum(rng.normal(0, 3, (frames, 3)), axis=0)  # a marker of another segment
    positions += rng.normal(0, 0.5, positions.shape)
    clean = distance_spread(positions, clip=np.inf)
    positions[1200, 1] += [0, 120.0, 0]
    positions[2100, 0] += [90.0, 0, 0]
    naive, kept = distance_spread(positions, clip=np.inf), distance_spread(positions)
    assert naive[0, 1] > 2.5 * clean[0, 1]  # the wrong samples alone
    assert kept[0, 1] == pytest.approx(clean[0, 1], rel=0.05)
    assert kept[0, 2] == pytest.approx(clean[0, 2], rel=0.05)  # a loose pair keeps its spread


@pytest.mark.parametrize("rig", ["human", "rods", "quadruped"])
def test_spectral_clustering_finds_the_true_segments_and_their_number(rig: str) -> None:
    rec = _recording(rig)
    assert sorted(cluster_spectral(rec.positions)) == _truth(rec)


@pytest.mark.parametrize("rig", ["human", "rods", "quadruped"])
def test_threshold_clustering_finds_the_true_segments(rig: str) -> None:
    rec = _recording(rig)
    truth = _truth(rec)
    assert sorted(cluster_distance_threshold(rec.positions)) == truth
    assert sorted(cluster_distance_threshold(rec.positions, linkage="single")) == truth
    assert sorted(cluster_distance_threshold(rec.positions, len(truth), threshold_mm=0.01)) == truth  # k wins


def test_spectral_clustering_with_a_given_number_and_the_eigengap() -> None:
    rec = _recording("human")
    spread = distance_spread(rec.positions)
    values, _ = spectral_embedding(spread)
    k = len(_truth(rec))
    assert eigengap_k(values) == k  # the largest drop of the spectrum comes after one eigenvalue per segment
    assert values[k - 1] - values[k] > 0.2
    merged = partition_spectral(spread, k - 1)
    assert len(merged) == k - 1 and sorted(m for group in merged for m in group) == list(range(len(rec.labels)))


def test_segment_names_use_the_common_label_prefix_else_the_body_part_the_labels_name() -> None:
    labels = ["LTH1", "LTH2", "LASI", "RASI", "RTH1", "RTH2", "X", "Y"]
    assert segment_names([[0, 1], [2, 3], [4, 5]], labels) == ["LTH", "pelvis", "RTH"]
    assert segment_names([[0, 1], [4, 5, 6]], labels) == ["LTH", "right_thigh"]
    assert segment_names([[0, 1], [6, 7]], labels) == ["LTH", "segment1"]  # labels that say nothing
    cmu = ["Sub:LTHI", "Sub:LKNE", "Sub:LSHN", "Sub:LANK", "Sub:LHEE", "Sub:LTOE", "Sub:C7", "Sub:T10", "Sub:RFWT",
           "Sub:LBWT", "Sub:LFHD", "Sub:RBHD", "Sub:LELB", "Sub:RUPA", "Sub:RTHI", "Sub:RKNE"]
    assert segment_names([[0, 1], [2, 3], [4, 5], [6, 7], [8, 9], [10, 11], [12], [14, 15]], cmu) == [
        "left_thigh", "left_shank", "left_foot", "trunk", "pelvis", "head", "segment6", "right_thigh"]


def test_real_lower_body_segments_match_the_expert_segmentation(data_dir: Path) -> None:
    from mocapflow.io.markers import read_markers

    data = read_markers(data_dir / "lowerbody_clusters_knee_0401.c3d")
    expert = [
        ["LASI", "RASI", "LPSI", "RPSI"],
        ["LSHL", "CLAV", "RSHL", "C7"],
        *[[f"{s}TH{i}" for i in range(1, 5)] for s in "LR"],
        *[[f"{s}MKN", f"{s}LKN", *(f"{s}SH{i}" for i in range(1, 5)), f"{s}LAK", f"{s}MAK"] for s in "LR"],
        *[[f"{s}TOE", f"{s}MT5", f"{s}CAL", f"{s}CUN"] for s in "LR"],
    ]
    found = [sorted(data.labels[i] for i in group) for group in cluster_spectral(data.positions)]
    assert sorted(found) == sorted(sorted(g) for g in expert)


@pytest.mark.parametrize("back_mm, expected", [
    (687.0, [[0, 1, 2], [3, 4, 5, 6]]),  # the back marker is not the trunk's nearest to the thigh: no move
    (400.0, [[0, 3], [1, 2], [4, 5, 6]]),  # it is: taken as the marker on their joint
])
def test_a_marker_takes_in_turn_only_the_joint_marker_of_a_group(back_mm: float, expected: list[list[int]]) -> None:
    """A thigh marker (0) robbed of its knee marker (1) by the shank marker (2) takes in turn its most rigid partner
    only when that one is the trunk's (3-6) nearest to it: a back marker 687 mm away that happened to keep still with
    it (cmu_85_02's first half) stays on the trunk."""
    spread = np.full((7, 7), 20.0)
    for (a, b), sd in {(0, 1): 1.2, (1, 2): 2.6, (0, 2): 9.0, (0, 3): 5.4, (0, 4): 6.8, (0, 5): 9.0, (0, 6): 9.0,
                       (3, 4): 2.0, (3, 5): 2.2, (3, 6): 3.8, (4, 5): 2.5, (4, 6): 3.0, (5, 6): 3.0}.items():
        spread[a, b] = spread[b, a] = sd
    np.fill_diagonal(spread, 0.0)
    distance = np.full((7, 7), 300.0)
    for b, mm in {3: back_mm, 4: 554.0, 5: 600.0, 6: 620.0}.items():
        distance[0, b] = distance[b, 0] = mm
    np.fill_diagonal(distance, 0.0)
    assert partition_rigidity(spread, distance=distance) == expected


def test_tracker_statistics_equal_the_batch_over_its_window() -> None:
    rec = _recording("rods")
    tracker = SegmentTracker(rec.labels, window=300, warmup=300, every=10 ** 9)
    for frame in rec.positions[:700]:
        tracker.update(frame)
    assert np.allclose(tracker.stats.spread(), distance_spread(rec.positions[400:700]), atol=1e-9)


def test_tracker_reports_after_warmup_and_only_when_the_partition_changes() -> None:
    rec = _recording("rods")
    labels = rec.labels
    rod1 = [i for i, s in enumerate(rec.marker_segment) if s == "rod1"]
    rod2 = [i for i, s in enumerate(rec.marker_segment) if s == "rod2"]
    # afterwards rod1 is glued to rod2: its markers follow rod2's motion in their first relative pose
    glued = rec.positions[:600].copy()
    start = rec.true_positions[0]
    c2 = start[rod2].mean(0)
    local = start[rod1] - c2
    from scipy.spatial.transform import Rotation

    for f in range(600):
        turn, _ = Rotation.align_vectors(rec.true_positions[f, rod2] - rec.true_positions[f, rod2].mean(0),
                                         start[rod2] - c2)
        glued[f, rod1] = turn.apply(local) + rec.true_positions[f, rod2].mean(0)
    tracker = SegmentTracker(labels, window=240, every=20)
    models = [(f, tracker.update(frame)) for f, frame in enumerate(np.concatenate([rec.positions[:600], glued]))]
    reported = [(f, m) for f, m in models if m is not None]
    assert reported[0][0] == 239  # first model right after one window of warm-up
    assert sorted(sorted(s.markers) for s in reported[0][1].segments) == sorted(
        sorted(labels[i] for i in g) for g in _truth(rec))
    assert len(reported) == 2  # unchanged partitions are not reported again; the glued rods are
    f, merged = reported[1]
    assert 600 < f <= 600 + 240 + 4 * 20  # within a window and the longest interval between two clusterings
    assert sorted(labels[i] for i in rod1 + rod2) in [sorted(s.markers) for s in merged.segments]


def test_pair_statistics_survive_adding_and_removing_many_frames() -> None:
    rng = np.random.default_rng(5)
    base = rng.normal(size=(4, 3)) * 100 + 5000  # far from the origin: cancellation would show
    frames = base + rng.normal(size=(20000, 4, 3)) * 0.01
    stats = PairStatistics(4)
    for chunk in np.array_split(frames, 40):
        d = stats.distances(chunk)
        stats.add(d)
        stats.add(d, -1.0)
    stats.add(stats.distances(frames[:1000]))
    assert np.allclose(stats.spread(), distance_spread(frames[:1000]), atol=1e-9)


def test_a_tracker_taking_on_new_markers_keeps_its_window() -> None:
    """The marker set only grows: a tracker that takes on a marker confirmed late holds the very distance statistics
    of one that had that marker (unseen) from the start, so its window is not thrown away, and places the marker."""
    rec = _recording("rods", 600)
    late = len(rec.labels) - 1
    positions = rec.positions.copy()
    start = 250
    positions[:start, late] = np.nan
    whole = SegmentTracker(rec.labels, window=200, warmup=100, every=20)
    grown = SegmentTracker(rec.labels[:late], window=200, warmup=100, every=20)
    models = []
    for f, frame in enumerate(positions):
        if f == start:
            grown.grow(rec.labels)
        whole.update(frame)
        models.append(grown.update(frame if f >= start else frame[:late]))
        if f >= start:
            for name in ("count", "total", "squares", "shift"):
                np.testing.assert_array_equal(getattr(grown.stats, name), getattr(whole.stats, name))
            np.testing.assert_array_equal(grown.stats.spread(), whole.stats.spread())
    placed = [m for m in models[start:] if m is not None]
    assert placed and any(rec.labels[late] in s.markers and len(s.markers) > 1 for s in placed[-1].segments)
    with pytest.raises(ValueError, match="do not extend"):
        grown.grow(rec.labels[::-1])
