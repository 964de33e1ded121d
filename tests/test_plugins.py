"""Pipeline nodes driven directly (the runtime's transport is tested elsewhere): what they publish, and when."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocapflow.io.skeleton import read_skeleton, write_skeleton
from mocapflow.messages import MarkerFrame, Segments, Skeleton
from mocapflow.mocap.model import Segment
from mocapflow.mocap.rigs import make_rig
from mocapflow.mocap.simulator import SimulatorConfig, simulate, truth_skeleton
from mocapflow.plugins.clusterer import ClustererConfig, SpectralClusterer
from mocapflow.plugins.joints import ClosedFormJoints, JointsConfig
from mocapflow.runtime.node import Node


def feed(node: Node, port: str, message: MarkerFrame) -> None:
    """Hand a data message to a node as the runtime does: only if the node wants it (a model stage samples)."""
    if node.wanted(port):
        node.process(port, message)


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
        feed(node, "markers", message)
    assert len(sent) == 1 and sent[0][0] == "segments" and sent[0][1].frame == 0
    assert sent[0][1].segments == read_skeleton(path).segments


def test_clusterer_learns_segments_after_its_warmup_and_repeats_only_changes() -> None:
    stream, _ = frames(400)
    assert stream[0].rate == 120
    sent: list[Segments] = []
    node = SpectralClusterer(ClustererConfig(warmup_s=1.0, every_s=0.25), lambda port, msg: sent.append(msg))
    for message in stream:
        feed(node, "markers", message)
    # 60 samples (one second at the default 60 Hz: every other frame, the first one included), then no change
    assert len(sent) == 1 and sent[0].frame == 118
    rig = make_rig("rods")
    truth = {frozenset(label for label, s in zip(rig.marker_labels, rig.marker_segment, strict=True) if s == k)
             for k in range(len(rig.segments))}
    assert {frozenset(s.markers) for s in sent[0].segments} == truth
    assert np.all([len(s.markers) >= 3 for s in sent[0].segments])


def test_joint_estimator_keeps_its_frames_when_new_markers_are_confirmed() -> None:
    """The labeller's marker list only grows: a marker confirmed late joins the estimator's window, which is not
    restarted, so the skeleton comes after half a window from the start, not from the last new marker."""
    rig = make_rig("human")
    rec = simulate(SimulatorConfig(rig="human", rate=120, seed=2), 360)
    counts = np.bincount(rig.marker_segment)
    late = int(np.flatnonzero(counts[rig.marker_segment] >= 4)[0])  # a marker whose segment keeps three without it
    order = [m for m in range(len(rec.labels)) if m != late] + [late]
    labels = [rec.labels[m] for m in order]
    segments = Segments(frame=0, capture_ns=0, segments=[
        Segment(name=name, markers=[m for m, k in zip(rig.marker_labels, rig.marker_segment, strict=True) if k == s])
        for s, name in enumerate(rig.segments)])
    sent: list[Skeleton] = []
    node = ClosedFormJoints(JointsConfig(window_s=2.0, every_s=1.0), lambda port, msg: sent.append(msg))
    node.process("segments", segments)
    for i, positions in enumerate(rec.positions[:, order]):
        known = len(labels) - 1 if i < 150 else len(labels)  # the last marker is confirmed at frame 150
        feed(node, "markers", MarkerFrame(frame=i, capture_ns=i, rate=120, positions=positions[:known],
                                          labels=labels[:known]))
    # half of the 2 s window (120 samples at 60 Hz: every other frame) after the first frame, then every second, the
    # new marker no reason to wait
    assert [message.frame for message in sent] == [118, 238, 358]
    assert rec.labels[late] not in {m for seg in sent[0].skeleton.segments for m in seg.markers}
    assert rec.labels[late] in {m for seg in sent[-1].skeleton.segments for m in seg.markers}
    assert len(sent[-1].skeleton.joints) == len(rig.segments) - 1


def test_closed_form_joint_estimator_places_a_two_marker_segment_down_the_tree() -> None:
    """A segment of two markers cannot fix its orientation for the closed form: the estimator places it from its
    neighbour, as the calibrate command does, instead of publishing no skeleton at all."""
    stream, labels = frames(480)
    rig = make_rig("rods")
    members = [[m for m, k in zip(rig.marker_labels, rig.marker_segment, strict=True) if k == s]
               for s in range(len(rig.segments))]
    members[-1] = members[-1][:2]
    sent: list[Skeleton] = []
    node = ClosedFormJoints(JointsConfig(window_s=4.0, every_s=4.0), lambda port, msg: sent.append(msg))
    node.process("segments", Segments(frame=0, capture_ns=0, segments=[
        Segment(name=name, markers=markers) for name, markers in zip(rig.segments, members, strict=True)]))
    for message in stream:
        feed(node, "markers", message)
    assert sent, "no skeleton"
    skeleton = sent[-1].skeleton
    assert len(skeleton.joints) == len(rig.segments) - 1
    assert {m for segment in skeleton.segments for m in segment.markers} == {m for g in members for m in g}


def test_an_unknown_plugin_is_one_line(capsys: pytest.CaptureFixture) -> None:
    from mocapflow.cli import main

    assert main(["plugins", "nosuch"]) == 2
    err = capsys.readouterr().err
    assert "unknown plugin 'nosuch'" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_nodes_written_against_either_api_run_and_derive_their_messages() -> None:
    """A node that builds itself in ``setup()`` and one that overrides ``__init__`` (the older way) both run; a message
    derived from a frame carries its frame number, capture time and rate."""
    from pydantic import BaseModel

    from mocapflow.runtime.node import Input, Node, Output, Publish

    class Gain(BaseModel):
        factor: float = 2.0

    class NewStyle(Node[Gain]):
        Config = Gain
        inputs = {"markers": Input(MarkerFrame)}
        outputs = {"markers": Output(MarkerFrame)}

        def setup(self) -> None:
            self.factor = self.config.factor

        def process(self, port: str, message: MarkerFrame) -> None:
            self.publish("markers", MarkerFrame.derive(message, positions=message.positions * self.factor))

    class OldStyle(Node):
        Config = Gain
        inputs = {"markers": Input(MarkerFrame)}
        outputs = {"markers": Output(MarkerFrame)}

        def __init__(self, config: Gain, publish: Publish, name: str = "old") -> None:
            super().__init__(config, publish, name)
            self.factor = -config.factor

        def process(self, port: str, message: MarkerFrame) -> None:
            self.publish("markers", MarkerFrame(frame=message.frame, capture_ns=message.capture_ns, rate=message.rate,
                                                positions=message.positions * self.factor))

    frame = MarkerFrame(frame=7, capture_ns=123, rate=240.0, positions=np.ones((2, 3)), labels=["a", "b"])
    for cls, factor in ((NewStyle, 3.0), (OldStyle, -3.0)):
        sent: list[tuple[str, MarkerFrame]] = []
        node = cls(Gain(factor=3.0), lambda port, message, out=sent: out.append((port, message)), "n")
        node.process("markers", frame)
        (port, out), = sent
        assert port == "markers" and (out.frame, out.capture_ns, out.rate) == (7, 123, 240.0)
        np.testing.assert_array_equal(out.positions, factor * np.ones((2, 3)))
    derived = Skeleton.derive(frame, skeleton=truth_skeleton(make_rig("rods"), simulate(
        SimulatorConfig(rig="rods", rate=120, noise_mm=0), 1).true_positions[0]))
    assert (derived.frame, derived.capture_ns) == (7, 123) and "rate" not in Skeleton.model_fields
