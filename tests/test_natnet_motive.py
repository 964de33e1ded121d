"""Real NatNet 3.0 traffic from OptiTrack Motive 2.1 (../shared/fixtures/natnet-motive21): the natnet adapter decodes
it to what OptiTrack's own SampleClient printed (frame ids, timestamps, marker positions), and the whole recorded
session, replayed over loopback UDP by ``mocapflow serve natnet``, flows through a graph to the recorder."""

from __future__ import annotations

import asyncio
import contextlib
import re
import threading
from pathlib import Path

import numpy as np
import pytest
from conftest import free_port
from scipy.optimize import linear_sum_assignment
from trackers import Server, graph_file, run_graph

from mocapflow.io.markers import read_markers
from mocapflow.messages import MarkerFrame

pytestmark = pytest.mark.integration
pytest.importorskip("natnet")

FIXTURES = Path(__file__).resolve().parents[2] / "shared" / "fixtures" / "natnet-motive21"
CAPTURE = FIXTURES / "raw" / "traffic.pcapng"
PRINTED_M = 0.005 + 1e-6  # SampleClient prints metres and seconds with two decimals (and rounds half to even)


@pytest.fixture
def motive() -> Path:
    if not CAPTURE.is_file():
        pytest.skip(f"recorded Motive session {CAPTURE} is absent")
    return FIXTURES


def sample_client() -> dict[int, tuple[float, list[tuple[int, int, bool, tuple[float, ...]]]]]:
    """Frame id -> (timestamp, [(model id, marker id, occluded, position)]) as SampleClient printed them."""
    frames: dict[int, tuple[float, list]] = {}
    frame = None
    for line in (FIXTURES / "raw" / "SampleClient_output.txt").read_text().splitlines():
        if line.startswith("FrameID : "):
            frame = int(line.split(":")[1])
        elif line.startswith("Timestamp : ") and frame is not None:
            frames[frame] = (float(line.split(":")[1]), [])
        elif line.startswith("Labeled Marker [") and frame is not None:
            model, marker, occluded = (int(v) for v in re.findall(r"(?:ModelID|MarkerID|Occluded)=(\d+)", line))
            pos = tuple(float(v) for v in re.search(r"pos=([^\]]+)\]", line).group(1).split(","))
            frames[frame][1].append((model, marker, bool(occluded), pos))
    return frames


def adapter_frames(port: int, markers: str) -> tuple[list[MarkerFrame], object]:
    """The natnet node, run the way the worker runs a source, against the server on ``port``: what it published."""
    from mocapflow.plugins.natnet import NatNetConfig, NatNetTracker

    published: list[MarkerFrame] = []
    node = NatNetTracker(NatNetConfig(command_port=port, multicast=False, markers=markers, end_after_s=1.5),
                         lambda _port, message: published.append(message))
    index = 0
    while node.emit(index):
        index += 1
    node.finish()
    return published, node


def motive_timestamps() -> dict[int, float]:
    """Frame id -> timestamp (s), as the natnet package decodes the recorded frames."""
    from natnet import DataFrame, Version
    from natnet.packet_buffer import PacketBuffer

    from mocapflow.trackers.natnet_server import Recording

    stamps = {}
    for _at, payload in Recording.read(CAPTURE).frames:
        buffer = PacketBuffer(payload)
        buffer.read("<HH")
        frame = DataFrame.read_from_buffer(buffer, Version(3, 0, 0, 0))
        stamps[frame.prefix.frame_number] = frame.suffix.timestamp
    return stamps


@pytest.mark.parametrize("markers", ["labelled", "unlabelled"])
def test_motive_session_decodes_to_sample_clients_values(markers: str, motive: Path) -> None:
    printed = sample_client()
    assert len(printed) == 251
    port = free_port()
    with Server("natnet", CAPTURE, port):
        published, node = adapter_frames(port, markers)
    assert [m.frame for m in published] == list(range(162734, 162734 + 518))  # the whole session, in order
    assert node.rate == 120.0  # Motive's 120 Hz, from its timestamps
    stamps = motive_timestamps()
    by_frame = {m.frame: m for m in published}
    for frame, (timestamp, labelled) in printed.items():
        assert abs(stamps[frame] - timestamp) <= PRINTED_M, frame
        message = by_frame[frame]
        if markers == "labelled":
            assert message.labels == [f"Marker{i}" for i in range(1, 6)]  # RaceQuad's markers, prefix dropped
            expected = np.full((5, 3), np.nan)
            for model, marker, _occluded, pos in labelled:
                if model == 2:
                    expected[marker - 1] = pos
        else:
            assert message.labels is None
            expected = np.array([pos for *_, pos in labelled])
            assert len(message.positions) == len(expected) == 6
            distance = np.linalg.norm(message.positions[:, None] / 1000 - expected[None], axis=2)
            rows, cols = linear_sum_assignment(distance)
            expected = expected[cols[np.argsort(rows)]]
        np.testing.assert_allclose(message.positions / 1000, expected, rtol=0, atol=PRINTED_M)
    # capture times: Motive's timestamps mapped to this machine's clock, never after the frame was published
    capture = np.array([m.capture_ns for m in published], dtype=np.int64)
    tracker = np.array([round(stamps[m.frame] * 1e9) for m in published], dtype=np.int64)
    offsets = capture - tracker
    # Frame-to-frame timing is Motive's, free of network jitter: the offset moves only when a packet arrives faster
    # than all before it (or, on a machine so busy that the 4.3 s session takes longer, when the window moves on).
    assert (np.diff(offsets) == 0).mean() > 0.9, np.diff(offsets)


def serve_in_thread(recording: object, port: int) -> tuple[threading.Thread, asyncio.AbstractEventLoop]:
    from mocapflow.trackers.natnet_server import NatNetServer

    loop = asyncio.new_event_loop()
    server = NatNetServer(recording)  # type: ignore[arg-type]
    ready = threading.Event()
    def run() -> None:
        with contextlib.suppress(RuntimeError):  # "event loop stopped": how the test ends the server
            loop.run_until_complete(server.serve("127.0.0.1", port, ready.set))

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    assert ready.wait(10)
    return thread, loop


@pytest.mark.parametrize("occluded", ["missing", "keep"])
def test_a_marker_motive_flags_occluded(occluded: str, motive: Path) -> None:
    """The recorded frame with an occluded marker (id 2 of model 7, position solved by Motive's model)."""
    from mocapflow.plugins.natnet import NatNetConfig, NatNetTracker
    from mocapflow.trackers.natnet_server import Recording

    frame = (motive / "mocapframe_packet_occluded_v3.bin").read_bytes()
    recording = Recording((motive / "serverinfo_packet_v3.bin").read_bytes(),
                          (motive / "modeldef_packet_v3.bin").read_bytes(),
                          [(0.0, frame), (1 / 120, frame[:4] + (269008).to_bytes(4, "little") + frame[8:])])
    port = free_port()
    thread, loop = serve_in_thread(recording, port)
    published: list[MarkerFrame] = []
    node = NatNetTracker(NatNetConfig(command_port=port, multicast=False, occluded=occluded, end_after_s=0.5, rate=120),
                         lambda _port, message: published.append(message))
    index = 0
    while node.emit(index):
        index += 1
    node.finish()
    loop.call_soon_threadsafe(loop.stop)
    thread.join(timeout=5)
    first = published[0]
    assert first.frame == 269007 and [m.frame for m in published] == [269007, 269008]
    # the described asset (RaceQuad, model 2) comes first and is not in this frame; model 7 is not described, so its
    # markers are named by their ids; its marker 1 is not in the frame at all
    assert first.labels[:5] == [f"Marker{i}" for i in range(1, 6)] and np.isnan(first.positions[:5]).all()
    if occluded == "keep":
        assert first.labels[5:] == ["7_2", "7_3", "7_4", "7_5"]
        np.testing.assert_allclose(first.positions[5], [-139.90189, 473.62429, 441.68669], atol=1e-3)
    else:
        assert first.labels[5:] == ["7_3", "7_4", "7_5"]
    np.testing.assert_allclose(first.positions[first.labels.index("7_3")], [-120.27807, 181.82461, 462.63772],
                               atol=1e-3)


def test_recorded_session_reaches_the_recorder_with_every_frame(motive: Path, tmp_path: Path,
                                                                 free_endpoint: str) -> None:
    port = free_port()
    graph = graph_file(tmp_path, free_endpoint, "motive", {
        "tracker": {"plugin": "natnet", "config": {"command_port": port, "multicast": False, "end_after_s": 5.0}},
        "recorder": {"plugin": "recorder", "inputs": {"markers": "tracker/markers"},
                     "config": {"path": str(tmp_path / "motive.trc")}},
    })
    with Server("natnet", CAPTURE, port):
        code, out, stats = run_graph(graph)
    assert code == 0 and "all nodes finished" in out, out
    assert stats["recorder"]["frames_in"] == 518 and stats["recorder"]["drops"] == 0, stats
    live = read_markers(tmp_path / "motive.trc")
    assert live.first_frame == 162734 and len(live.positions) == 518 and live.rate == 120.0
    assert live.labels == [f"Marker{i}" for i in range(1, 6)]
    first = sample_client()[162734][1]
    expected = [pos for model, _marker, _occluded, pos in first if model == 2]
    np.testing.assert_allclose(live.positions[0] / 1000, expected, rtol=0, atol=PRINTED_M)
    assert np.isfinite(live.positions).all()
