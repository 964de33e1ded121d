"""Pipeline nodes driven directly (the runtime's transport is tested elsewhere): what they publish, and when."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mocapflow.io.skeleton import read_skeleton, write_skeleton
from mocapflow.messages import MarkerFrame, Segments
from mocapflow.mocap.rigs import make_rig
from mocapflow.mocap.simulator import SimulatorConfig, simulate, truth_skeleton
from mocapflow.plugins.clusterer import ClustererConfig, SpectralClusterer


def frames(n: int) -> tuple[list[MarkerFrame], list[str]]:
    rec = simulate(SimulatorConfig(rig="rods", rate=120, seed=2), n)
    return [MarkerFrame(frame=i, capture_ns=i, rate=120, positions=p, labels=rec.labels)
            for i, p in enumerate(rec.positions)], rec.labels


def test_clusterer_seeded_with_a_skeleton_publishes_its_segments_at_once(tmp_path: Path) -> None:
    stream, _ = frames(10)
    rec = simulate(SimulatorConfig(rig="rods", rate=120, noise_mm=0), 1)
    path = tmp_path / "rods.json"
    write_skeleton(path, truth_skeleton(make_rig("rods"), rec.true_positions[0]))
    sent: list[tuple[str, Segments]] = []
    node = SpectralClusterer(ClustererConfig(skeleton=str(path)), lambda port, msg: sent.append((port, msg)))
    for message in stream:
        node.process("markers", message)
    assert len(sent) == 1 and sent[0][0] == "segments" and sent[0][1].frame == 0
    assert sent[0][1].segments == read_skeleton(path).segments


def test_clusterer_learns_segments_after_its_window_and_repeats_only_changes() -> None:
    stream, _ = frames(400)
    sent: list[Segments] = []
    node = SpectralClusterer(ClustererConfig(window_s=1.0, every_s=0.25), lambda port, msg: sent.append(msg))
    for message in stream:
        node.process("markers", message)
    assert len(sent) == 1 and sent[0].frame == 119  # after one window, then no change
    rig = make_rig("rods")
    truth = {frozenset(label for label, s in zip(rig.marker_labels, rig.marker_segment, strict=True) if s == k)
             for k in range(len(rig.segments))}
    assert {frozenset(s.markers) for s in sent[0].segments} == truth
    assert np.all([len(s.markers) >= 3 for s in sent[0].segments])
