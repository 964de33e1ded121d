"""The labeller-filler feedback loop in a node group does not race: the filler's prediction for frame n+1 reaches the
labeller before the tracker's frame n+1, so live labelling over real Zenoh equals the same nodes driven offline, frame
by frame, in order. The capture is replayed at ten times its rate, faster than the group labels it, so frames queue up
and are caught up on: even then each waits for the prediction of the one before. The filler has the subject's
skeleton, so it predicts the markers of a whole hidden segment through its joints, and those predictions decide
labels the labeller could not: without them the same capture is labelled otherwise."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import orjson
import pytest
import zenoh
from conftest import run_cli

from mocapflow.io.markerdata import MarkerData
from mocapflow.io.markers import write_markers
from mocapflow.io.skeleton import write_skeleton
from mocapflow.messages import MarkerFrame, decode, encode
from mocapflow.mocap.calibration import calibrate
from mocapflow.mocap.simulator import SimulatorConfig, simulate
from mocapflow.runtime.plugins import load
from mocapflow.runtime.session import open_router

FRAMES = 400
CALIBRATION = 1000  # frames of the same subject before the replayed ones


def gapped_capture(tmp_path: Path) -> tuple[Path, Path]:
    """A simulated human's capture, its left forearm and then its right shank hidden whole for half a second, their
    markers coming back one by one (where the filler's predictions count); and the subject's skeleton calibrated on
    an earlier trial under the names the labeller gives the markers (``M001``...), as the model stages would give
    it live. Returns the capture and the skeleton."""
    rec = simulate(SimulatorConfig(rig="human", rate=120, noise_mm=0.5, seed=5, dropout_rate=0, long_gaps=0),
                   CALIBRATION + FRAMES)
    clean = rec.positions[CALIBRATION:]
    positions = clean.copy()
    for label, start, stop in [("LFA1", 100, 160), ("LFA2", 100, 170), ("LFA3", 100, 180), ("RSH1", 220, 280),
                               ("RSH2", 220, 290), ("RSH3", 220, 300), ("RSH4", 220, 310)]:
        positions[start:stop, rec.labels.index(label)] = np.nan
    source, unhidden = tmp_path / "gapped.c3d", tmp_path / "clean.c3d"
    write_markers(source, MarkerData(positions, rec.labels, rec.rate, 1))
    write_markers(unhidden, MarkerData(clean, rec.labels, rec.rate, 1))
    # the first frames, which name every marker, are the same in both: the names are the clean capture's
    last = offline(unhidden, feedback=False)[-1]
    named = np.array(last["positions"], float).reshape(-1, 3)
    names = {}
    for label, position in zip(last["labels"], named, strict=True):
        if np.isfinite(position).all():
            names[rec.labels[int(np.argmin(np.linalg.norm(clean[-1] - position, axis=1)))]] = label
    assert len(names) == len(rec.labels)
    skeleton = tmp_path / "skeleton.json"
    write_skeleton(skeleton, calibrate(rec.positions[:CALIBRATION], [names[m] for m in rec.labels], rec.rate))
    return source, skeleton


def offline(source: Path, feedback: bool = True, wire: bool = False,
            skeleton: Path | None = None) -> list[dict[str, Any]]:
    """Replay, labeller and filler (with ``skeleton``) driven directly: each frame labelled, filled, its prediction
    handed back (unless not ``feedback``). The tracker's frames come to the labeller as decoded from the wire; with
    ``wire`` so does every message (each node in its own process)."""
    def hop(message: MarkerFrame, crosses: bool = True) -> MarkerFrame:
        return decode(encode(message), MarkerFrame) if crosses else message

    sent: list[tuple[str, str, Any]] = []

    def make(plugin: str, name: str, config: dict[str, Any]) -> Any:
        cls = load(plugin)
        return cls(cls.Config.model_validate(config), lambda port, msg: sent.append((name, port, msg)), name)

    tracker = make("c3d-replay", "tracker", {"path": str(source), "unlabelled": True})
    labeller = make("labeller", "labeller", {})
    filler = make("occlusion-filler", "filler", {"skeleton": str(skeleton)} if skeleton else {})
    labelled = []
    index = 0
    while tracker.emit(index):
        index += 1
        while sent:
            name, port, msg = sent.pop(0)
            if name == "tracker":
                labeller.process("markers", hop(msg))
            elif name == "labeller":
                labelled.append(msg)
                filler.process("markers", hop(msg, wire))
            elif port == "predictions" and feedback:
                labeller.process("predictions", hop(msg, wire))
    return [_comparable(encode(m)) for m in labelled]


def _comparable(payload: bytes) -> dict[str, Any]:
    message = orjson.loads(payload)
    message.pop("capture_ns")
    return message


@pytest.mark.integration
@pytest.mark.parametrize("layout", ["grouped", "separate"])
def test_live_labelling_equals_offline(tmp_path: Path, free_endpoint: str, layout: str) -> None:
    """Grouped, the prediction is handed over first; separate, the labeller waits for it (up to a bound generous
    for a loaded machine) and counts the frames it labelled without one: only the first, which has none."""
    source, skeleton = gapped_capture(tmp_path)
    path = tmp_path / "fb.yaml"
    placing = ", group: frame" if layout == "grouped" else ""
    path.write_text(
        "name: fb\nnodes:\n"
        f"  tracker: {{plugin: c3d-replay, config: {{path: '{source}', unlabelled: true, speed: 10}}}}\n"
        "  labeller: {plugin: labeller, inputs: {markers: tracker/markers, predictions: filler/predictions},"
        f" wait_for: {{predictions: 2000}}{placing}}}\n"
        f"  filler: {{plugin: occlusion-filler, inputs: {{markers: labeller/markers}},"
        f" config: {{skeleton: '{skeleton}'}}{placing}}}\n"
    )
    live: list[dict[str, Any]] = []

    def on_sample(sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            live.append(_comparable(sample.payload.to_bytes()))

    with open_router([free_endpoint]) as router:
        sub = router.declare_subscriber("mocapflow/fb/labeller/markers", on_sample)
        done = run_cli("run", path, "--connect", free_endpoint, "--summary", tmp_path / "s.json", timeout=120)
        time.sleep(0.3)
        sub.undeclare()
    assert done.returncode == 0, done.stdout + done.stderr
    reference = offline(source, wire=layout == "separate", skeleton=skeleton)
    stats = orjson.loads((tmp_path / "s.json").read_bytes())["labeller"]
    assert stats["unpaired"] == (0 if layout == "grouped" else 1), stats
    assert len(reference) == FRAMES and len(live) == len(reference)
    assert [m["frame"] for m in live] == [m["frame"] for m in reference]
    assert live == reference  # labels, positions and rays of every frame
    assert len(reference[-1]["labels"]) > 10  # it did label the capture
    # and the predictions did count: without them the same capture is labelled otherwise, the hidden segments' markers
    # coming back under more new labels
    alone = offline(source, feedback=False, skeleton=skeleton)
    assert sum(a != b for a, b in zip(alone, reference, strict=True)) > FRAMES // 10
    assert len(alone[-1]["labels"]) > len(reference[-1]["labels"])
