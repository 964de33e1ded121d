"""The stand-in servers against the vendors' own clients, over real sockets on loopback: Qualisys's ``qtm-rt`` SDK
and the ``natnet`` client read the file's frames, labels and rate exactly."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import free_port
from trackers import Server

from mocapflow.io.markers import read_markers
from mocapflow.plugins.natnet import enlarge_receive_buffers

pytestmark = pytest.mark.integration
qtm_rt = pytest.importorskip("qtm_rt")
natnet = pytest.importorskip("natnet")

GAPPY = "lowerbody_clusters_knee_0401.c3d"  # real gaps: NaN in the labelled stream, absent from the point cloud
SHORT = "cmu_dribble_shoot_basketball.c3d"


async def qtm_stream(port: int, component: str, frames: int) -> tuple[str, list]:
    events: list = []
    connection = await qtm_rt.connect("127.0.0.1", port, on_event=events.append)
    assert connection is not None
    parameters = await connection.get_parameters(["general", "3d"])
    packets: list = []
    await connection.stream_frames(components=[component], on_packet=packets.append)
    for _ in range(1200):
        if qtm_rt.QRTEvent.EventRTfromFileStopped in events:
            break
        await asyncio.sleep(0.05)
    assert events == [qtm_rt.QRTEvent.EventRTfromFileStopped]  # the end of the file, after its frames
    connection.disconnect()
    return parameters.decode(), packets


def test_qtm_rt_reads_the_file_exactly(real_file) -> None:
    path = real_file(GAPPY)
    data = read_markers(path)
    n = len(data.positions)
    port = free_port()
    with Server("qtm", path, port, "--speed", "10"):
        xml, packets = asyncio.run(qtm_stream(port, "3d", n))
    assert f"<Frequency>{data.rate:g}</Frequency>" in xml
    labels = [name.split("</Name>")[0] for name in xml.split("<Name>")[1:]]
    assert labels == data.labels
    assert [p.framenumber for p in packets] == list(range(data.first_frame, data.first_frame + n))
    stamps = np.array([p.timestamp for p in packets])
    np.testing.assert_allclose(np.diff(stamps), 1e6 / data.rate, atol=1)  # microseconds of capture time
    received = np.array([[tuple(m) for m in p.get_3d_markers()[1]] for p in packets])
    expected = data.positions.astype(np.float32)
    assert np.isnan(expected).any()
    np.testing.assert_array_equal(received, expected)


def test_qtm_rt_reads_the_point_cloud_exactly(real_file) -> None:
    path = real_file(GAPPY)
    data = read_markers(path)
    port = free_port()
    with Server("qtm", path, port, "--speed", "10"):
        _, packets = asyncio.run(qtm_stream(port, "3dnolabels", len(data.positions)))
    assert len(packets) == len(data.positions)
    for packet, expected in zip(packets, data.positions.astype(np.float32), strict=True):
        points = np.array([m[:3] for m in packet.get_3d_markers_no_label()[1]], dtype=np.float32).reshape(-1, 3)
        seen = expected[np.isfinite(expected).all(axis=1)]
        np.testing.assert_array_equal(np.unique(points, axis=0), np.unique(seen, axis=0))


def test_natnet_client_reads_the_file_exactly(real_file) -> None:
    path = real_file(SHORT)
    data = read_markers(path)
    # NatNet streams over UDP, which may drop a datagram on a machine busy enough: a session that lost one is played
    # again (at most three times); what is checked is that the server sends every frame as the file has it. A
    # session is over when every frame came, or none for 2 s after the first (the file played, a frame lost).
    for _attempt in range(3):
        port = free_port()
        frames: list = []
        descriptions: list = []
        arrived = [0.0]

        def received(frame: object, frames: list = frames, arrived: list[float] = arrived) -> None:
            frames.append(frame)
            arrived[0] = time.monotonic()

        with Server("natnet", path, port, "--speed", "2"):
            client = natnet.NatNetClient(server_ip_address="127.0.0.1", local_ip_address="127.0.0.1",
                                         use_multicast=False, command_port=port)
            client.on_data_frame_received_event.handlers.append(received)
            client.on_data_description_received_event.handlers.append(descriptions.append)
            with client:
                enlarge_receive_buffers(client)  # as the adapter does: a busy machine must not overflow the socket
                assert str(client.server_info.nat_net_protocol_version) == "3.0.0.0"
                client.request_modeldef()
                client.run_async()
                deadline = time.monotonic() + 60
                while (len(frames) < len(data.positions) and time.monotonic() < deadline
                       and not (frames and time.monotonic() - arrived[0] > 2.0)):
                    time.sleep(0.05)
        numbers = [f.prefix.frame_number for f in frames]
        if numbers == list(range(data.first_frame, data.first_frame + len(data.positions))):
            break
    assert [f.prefix.frame_number for f in frames] == list(range(data.first_frame, data.first_frame + len(frames)))
    assert len(frames) == len(data.positions)
    (marker_set,) = descriptions[0].marker_sets
    assert list(marker_set.marker_names) == data.labels and marker_set.name == path.stem
    assert [(s.name, s.id_num) for s in descriptions[0].skeletons] == [(path.stem, 1)]
    stamps = np.array([f.suffix.timestamp for f in frames])
    np.testing.assert_allclose(np.diff(stamps), 1 / data.rate, atol=1e-9)
    metres = (data.positions / 1000).astype(np.float32)
    received = np.array([f.marker_sets[0].marker_pos_list for f in frames], dtype=np.float32)
    np.testing.assert_array_equal(received, metres)
    for frame, expected in zip(frames, metres, strict=True):
        seen = np.flatnonzero(np.isfinite(expected).all(axis=1))
        assert [m.model_id for m in frame.labeled_markers] == [1] * len(seen)
        assert [m.marker_id for m in frame.labeled_markers] == list(seen + 1)
        np.testing.assert_array_equal(np.array([m.pos for m in frame.labeled_markers], np.float32), expected[seen])


def test_serve_refuses_a_file_it_cannot_read_in_one_line(tmp_path: Path) -> None:
    import subprocess

    from conftest import CLI

    bad = tmp_path / "notes.c3d"
    bad.write_text("not a capture")
    done = subprocess.run([*CLI, "serve", "qtm", str(bad), "--port", str(free_port())], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert done.stderr.startswith(f"mocapflow serve: error: {bad}"), done.stderr


def test_qtm_adapter_decimates_with_consecutive_numbers(real_file) -> None:
    """``divisor: 2``: QTM streams every other frame; the adapter numbers them one apart at half the rate."""
    from mocapflow.plugins.qtm import QtmConfig, QtmTracker

    path = real_file(SHORT)
    data = read_markers(path)
    port = free_port()
    published: list = []
    with Server("qtm", path, port, "--speed", "4"):
        node = QtmTracker(QtmConfig(port=port, divisor=2, end_with_capture=True),
                          lambda _port, message: published.append(message))
        index = 0
        while node.emit(index):
            index += 1
        node.finish()
    assert node.rate == data.rate / 2 and all(m.rate == data.rate / 2 for m in published)
    rows = [r for r in range(len(data.positions)) if r % 2 == 0]  # the stand-in sends frames 0, 2, 4... of the file
    assert [m.frame for m in published] == [(data.first_frame + r) // 2 for r in rows]
    np.testing.assert_array_equal(np.array([m.positions for m in published]), data.positions[rows].astype(np.float32))
