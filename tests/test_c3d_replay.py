"""The file tracker on its own: what it streams from C3D and TRC files, real exporters' quirks included."""

from __future__ import annotations

from pathlib import Path

import ezc3d
import numpy as np
import pytest

from mocapflow.errors import MocapFileError
from mocapflow.io.markers import MarkerData, write_markers
from mocapflow.messages import MarkerFrame
from mocapflow.plugins.c3d_replay import FileReplay, ReplayConfig

RATE = 100.0


def recording(frames: int = 30, markers: int = 5, first_frame: int = 11) -> MarkerData:
    rng = np.random.default_rng(4)
    positions = rng.uniform(-1000.0, 1000.0, (frames, markers, 3))
    positions[3:7, 2] = np.nan
    return MarkerData(positions, [f"M{i}" for i in range(markers)], RATE, first_frame)


def replay(path: Path, **config: object) -> tuple[FileReplay, list[MarkerFrame]]:
    sent: list[MarkerFrame] = []
    node = FileReplay(ReplayConfig(path=str(path), **config), lambda port, message: sent.append(message))
    return node, sent


def stream(node: FileReplay, limit: int = 10_000) -> int:
    """Emit until the node says the file is done (at most ``limit`` frames); the number of frames sent."""
    index = 0
    while index < limit and node.emit(index):
        index += 1
    return index


@pytest.mark.parametrize("suffix", ["c3d", "trc"])
def test_every_frame_in_order_with_the_files_numbers_labels_and_rate(suffix: str, tmp_path: Path) -> None:
    data = recording()
    path = tmp_path / f"trial.{suffix}"
    write_markers(path, data)
    node, sent = replay(path, speed=2.0)
    assert node.rate == 2 * RATE  # paced twice as fast...
    assert stream(node) == data.n_frames
    assert all(m.rate == RATE for m in sent)  # ...but the frames still say how they were captured
    assert [m.frame for m in sent] == list(range(11, 11 + data.n_frames))
    assert all(m.labels == data.labels for m in sent)
    np.testing.assert_allclose(np.stack([m.positions for m in sent]), data.positions, atol=1e-3)


def test_start_end_and_loop(tmp_path: Path) -> None:
    data = recording()
    path = tmp_path / "trial.c3d"
    write_markers(path, data)
    node, sent = replay(path, start=5, end=15, loop=True)
    assert stream(node, limit=25) == 25
    assert [m.frame for m in sent] == list(range(16, 41))  # numbers keep rising through the loop
    rows = np.stack([m.positions for m in sent])
    np.testing.assert_array_equal(rows[:10], rows[10:20])
    np.testing.assert_allclose(rows[:10], data.positions[5:15], atol=1e-3)
    with pytest.raises(ValueError, match="past the last frame"):
        replay(path, start=40)


def test_unlabelled_mode_strips_identities_and_shuffles(tmp_path: Path) -> None:
    data = recording(markers=8)
    path = tmp_path / "trial.c3d"
    write_markers(path, data)
    node, sent = replay(path, unlabelled=True, seed=3)
    stream(node)
    shuffled = 0
    for message, truth in zip(sent, data.positions.astype(np.float32), strict=True):
        assert message.labels is None
        seen = truth[np.isfinite(truth).all(1)]
        assert len(message.positions) == len(seen)  # missing markers are simply absent
        order = [int(np.flatnonzero((seen == p).all(1))[0]) for p in message.positions]
        assert sorted(order) == list(range(len(seen)))
        shuffled += order != sorted(order)
    assert shuffled > len(sent) // 2
    node, again = replay(path, unlabelled=True, seed=3)
    stream(node)
    assert all(np.array_equal(a.positions, b.positions) for a, b in zip(sent, again, strict=True))


def test_real_exporter_quirks(tmp_path: Path) -> None:
    """Metres, ``Subject:`` prefixes, more than 255 labels (POINT:LABELS2), zeros for gaps, analog channels."""
    frames, markers = 12, 300
    rng = np.random.default_rng(0)
    metres = rng.uniform(-2.0, 2.0, (frames, markers, 3))
    metres[4:6, 7] = 0.0
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = np.array([RATE])
    c3d["parameters"]["POINT"]["UNITS"]["value"] = ["m"]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = [f"Male:M{i:03d}" for i in range(markers)]
    points = np.ones((4, markers, frames))
    points[:3] = metres.transpose(2, 1, 0)
    c3d["data"]["points"] = points
    c3d["parameters"]["ANALOG"]["RATE"]["value"] = np.array([10 * RATE])
    c3d["parameters"]["ANALOG"]["USED"]["value"] = np.array([2])
    c3d["parameters"]["ANALOG"]["LABELS"]["value"] = ["EMG1", "EMG2"]
    c3d["data"]["analogs"] = rng.normal(size=(1, 2, 10 * frames))
    c3d.write(str(tmp_path / "vicon.c3d"))
    assert "LABELS2" in ezc3d.c3d(str(tmp_path / "vicon.c3d"))["parameters"]["POINT"]

    node, sent = replay(tmp_path / "vicon.c3d")
    assert stream(node) == frames
    assert sent[0].labels == [f"M{i:03d}" for i in range(markers)]
    rows = np.stack([m.positions for m in sent]).astype(np.float64)
    expected = metres * 1000.0
    expected[4:6, 7] = np.nan
    np.testing.assert_allclose(rows, expected, rtol=1e-6, atol=1e-3)


@pytest.mark.parametrize("content, reason", [(b"a text file\n" * 50, "not a C3D file"), (b"", "not a C3D file")])
def test_unreadable_file_stops_the_node_naming_the_file(content: bytes, reason: str, tmp_path: Path) -> None:
    path = tmp_path / "notes.c3d"
    path.write_bytes(content)
    with pytest.raises(MocapFileError, match=f"notes.c3d: {reason}") as info:
        replay(path)
    assert "\n" not in str(info.value)


def test_file_with_no_position_at_all(tmp_path: Path) -> None:
    data = recording()
    data.positions[:] = np.nan
    write_markers(tmp_path / "empty.trc", data)
    with pytest.raises(ValueError, match="empty.trc: no marker position"):
        replay(tmp_path / "empty.trc")
