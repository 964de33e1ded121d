"""The wire codec: exact round trips, NaN as null, clear errors, schemas, and a reader with no mocapflow."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import orjson
import pytest

from mocapflow.messages import (
    MESSAGE_TYPES,
    DecodeError,
    MarkerFrame,
    Pose,
    SimTruth,
    Skeleton,
    decode,
    encode,
    json_schema,
)
from mocapflow.mocap.model import Joint, Segment, SkeletonModel


def frame(n: int = 60) -> MarkerFrame:
    rng = np.random.default_rng(1)
    positions = (rng.normal(size=(n, 3)) * 500).astype(np.float32)
    positions[[3, n - 2]] = np.nan
    flags = np.ones(n, np.uint8)
    flags[[3, n - 2]] = 0
    return MarkerFrame(frame=42, capture_ns=1_700_000_000_123_456_789, rate=240.0, positions=positions,
                       labels=[f"M{i:03d}" for i in range(n)], flags=flags)


def test_marker_frame_round_trip_is_exact() -> None:
    original = frame()
    back = decode(encode(original), MarkerFrame)
    assert back.frame == 42 and back.capture_ns == original.capture_ns and back.labels == original.labels
    np.testing.assert_array_equal(back.positions, original.positions)  # NaN == NaN here
    assert back.positions.dtype == np.float32 and back.positions.shape == (60, 3)
    np.testing.assert_array_equal(back.flags, original.flags)


def test_a_flat_message_is_written_as_pydantic_writes_it() -> None:
    """``encode`` writes frames and poses from their fields directly: byte for byte what pydantic's serialiser
    gives, whichever optional fields are set, and after a copy with changes."""
    def by_pydantic(message: MarkerFrame | Pose | SimTruth) -> bytes:
        return orjson.dumps(message.model_dump(mode="python"), option=orjson.OPT_SERIALIZE_NUMPY)

    full = frame()
    rays = np.full((60, 6), np.nan)
    rays[3] = [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    messages = [full, full.model_copy(update={"positions": full.positions[::-1] * 2}),
                MarkerFrame(frame=0, capture_ns=0, rate=100.0, positions=np.zeros((0, 3))),
                MarkerFrame.derive(full, positions=full.positions, rays=rays),
                Pose(frame=1, capture_ns=2, joint_names=["a-b"], joint_centres=np.full((1, 3), np.nan),
                     segment_names=["a", "b"], rotations=np.eye(4)[:2], translations=np.ones((2, 3))),
                SimTruth(frame=3, capture_ns=4, labels=["m1", "m2"], identity=np.array([1, -1, 0]),
                         true_positions=np.ones((2, 3)), joint_names=[], joint_centres=np.zeros((0, 3)))]
    for message in messages:
        assert encode(message) == by_pydantic(message)


def test_missing_values_travel_as_null() -> None:
    data = json.loads(encode(frame()))
    assert data["positions"][9:12] == [None, None, None]
    assert len(data["positions"]) == 180


def test_model_messages_round_trip() -> None:
    skeleton = SkeletonModel(
        segments=[Segment(name="a", markers=["m1", "m2", "m3"]), Segment(name="b", markers=["m4", "m5"])],
        joints=[Joint(name="a-b", parent="a", child="b", parent_offset=(1.0, 2.0, 3.0))], root="a",
    )
    msg = Skeleton(frame=5, capture_ns=1, skeleton=skeleton)
    assert decode(encode(msg), Skeleton) == msg
    pose = Pose(frame=1, capture_ns=2, joint_names=["a-b"], joint_centres=np.zeros((1, 3)), segment_names=["a", "b"],
                rotations=np.tile([0.0, 0.0, 0.0, 1.0], (2, 1)), translations=np.ones((2, 3)))
    back = decode(encode(pose), Pose)
    np.testing.assert_array_equal(back.rotations, pose.rotations)


@pytest.mark.parametrize(
    "payload, reason",
    [
        (b"\xff\xfe not json", "not JSON"),
        (b"[1, 2, 3]", "expected a JSON object"),
        (b'{"frame": 1, "capture_ns": 5, "rate": 100, "positions": [1, 2]}', "positions"),
        (b'{"frame": 1, "capture_ns": 5, "rate": 100, "positions": [1, 2, 3], "labels": ["a", "b"]}', "labels"),
        (b'{"frame": -1, "capture_ns": 5, "rate": 100, "positions": []}', "frame"),
        (b'{"frame": 1, "capture_ns": 5, "rate": 100, "positions": ["x", 1, 2]}', "positions"),
        (b'{"frame": 1, "capture_ns": 5, "rate": 100, "positions": [], "colour": 1}', "colour"),
    ],
)
def test_malformed_payloads_get_a_clear_error(payload: bytes, reason: str) -> None:
    with pytest.raises(DecodeError, match=reason):
        decode(payload, MarkerFrame)


def test_observed_positions_leave_out_estimated_samples() -> None:
    positions = np.arange(12.0).reshape(4, 3)
    frame = MarkerFrame(frame=0, capture_ns=0, rate=100.0, positions=positions, flags=np.array([1, 2, 0, 8], np.uint8))
    observed = frame.observed()
    np.testing.assert_array_equal(observed[0], positions[0])
    assert np.isnan(observed[1:]).all()
    np.testing.assert_array_equal(MarkerFrame(frame=0, capture_ns=0, rate=100.0, positions=positions).observed(),
                                  positions)


def test_empty_frame_is_valid() -> None:
    empty = MarkerFrame(frame=0, capture_ns=0, rate=100, positions=np.zeros((0, 3)))
    assert decode(encode(empty), MarkerFrame).positions.shape == (0, 3)


def test_every_type_has_a_json_schema_that_validates_its_wire_form() -> None:
    jsonschema = pytest.importorskip("jsonschema")
    for name, cls in MESSAGE_TYPES.items():
        schema = json_schema(cls)
        assert schema["$id"] == f"mocapflow/{name}"
    jsonschema.validate(json.loads(encode(frame())), json_schema(MarkerFrame))


FOREIGN_READER = textwrap.dedent(
    """
    # A client that knows only Zenoh, JSON and numpy: it must not import mocapflow.
    import json, sys, threading
    import numpy as np
    import zenoh
    assert "mocapflow" not in sys.modules
    endpoint, key = sys.argv[1], sys.argv[2]
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    got = threading.Event()
    def on_sample(sample):
        msg = json.loads(sample.payload.to_bytes())
        pos = np.array([np.nan if v is None else v for v in msg["positions"]], dtype=np.float32).reshape(-1, 3)
        print(json.dumps({"encoding": str(sample.encoding), "frame": msg["frame"], "labels": msg["labels"],
                          "positions": [[None if np.isnan(v) else float(v) for v in row] for row in pos]}))
        got.set()
    with zenoh.open(conf) as session:
        sub = session.declare_subscriber(key, on_sample)
        print("ready", flush=True)
        got.wait(10)
    """
)


@pytest.mark.integration
def test_a_client_without_mocapflow_decodes_a_frame(tmp_path: Path, free_endpoint: str) -> None:
    from mocapflow.runtime.session import open_router

    script = tmp_path / "reader.py"
    script.write_text(FOREIGN_READER)
    key = "mocapflow/test/tracker/markers"
    original = frame(5)
    with open_router([free_endpoint]) as router:
        reader = subprocess.Popen([sys.executable, str(script), free_endpoint, key], stdout=subprocess.PIPE,
                                  text=True, cwd=tmp_path)
        assert reader.stdout.readline().strip() == "ready"
        import time

        import zenoh

        publisher = router.declare_publisher(key, encoding=zenoh.Encoding(MarkerFrame.encoding()))
        out = ""
        for _ in range(50):  # until the reader's subscription has reached the router
            publisher.put(encode(original))
            time.sleep(0.1)
            if reader.poll() is not None:
                break
        out = reader.communicate(timeout=10)[0]
    result = json.loads(out.strip().splitlines()[-1])
    assert result["encoding"] == "application/json;mocapflow/MarkerFrame"
    assert result["frame"] == 42 and result["labels"] == original.labels
    decoded = np.array([[np.nan if v is None else v for v in row] for row in result["positions"]], dtype=np.float32)
    np.testing.assert_array_equal(decoded, original.positions)
