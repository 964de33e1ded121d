"""The labeller-filler feedback loop in a node group does not race: the filler's prediction for frame n+1 reaches the
labeller before the tracker's frame n+1, so live labelling of a real capture over real Zenoh equals the same nodes
driven offline, frame by frame, in order. The capture is replayed at ten times its rate, faster than the group
labels it, so frames queue up and are caught up on: even then each waits for the prediction of the one before."""

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
from mocapflow.io.markers import read_markers, write_markers
from mocapflow.messages import MarkerFrame, decode, encode
from mocapflow.runtime.plugins import load
from mocapflow.runtime.session import open_router

FRAMES = 400


def gapped_slice(data_dir: Path, path: Path) -> None:
    """Four seconds of a real lower-body capture with markers hidden for a while, to be found again when they
    reappear (where the filler's predictions count)."""
    data = read_markers(data_dir / "lowerbody_clusters_knee_0401.c3d")
    rows = slice(1000, 1000 + FRAMES)
    positions = data.positions[rows].copy()
    for label, start, stop in [("LTH2", 100, 160), ("RSH3", 200, 230), ("LASI", 300, 310), ("LSH1", 250, 290),
                               ("LSH2", 250, 290), ("RTOE", 120, 200)]:
        positions[start:stop, data.labels.index(label)] = np.nan
    write_markers(path, MarkerData(positions, data.labels, data.rate, data.first_frame + rows.start))


def offline(source: Path, feedback: bool = True, wire: bool = False) -> list[dict[str, Any]]:
    """Replay, labeller and filler driven directly: each frame labelled, filled, its prediction handed back (unless
    not ``feedback``). The tracker's frames come to the labeller as decoded from the wire; with ``wire`` so does
    every message (each node in its own process)."""
    def hop(message: MarkerFrame, crosses: bool = True) -> MarkerFrame:
        return decode(encode(message), MarkerFrame) if crosses else message

    sent: list[tuple[str, str, Any]] = []

    def make(plugin: str, name: str, config: dict[str, Any]) -> Any:
        cls = load(plugin)
        return cls(cls.Config.model_validate(config), lambda port, msg: sent.append((name, port, msg)), name)

    tracker = make("c3d-replay", "tracker", {"path": str(source), "unlabelled": True})
    labeller = make("labeller", "labeller", {})
    filler = make("occlusion-filler", "filler", {})
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
def test_live_labelling_equals_offline(tmp_path: Path, free_endpoint: str, data_dir: Path, layout: str) -> None:
    """Grouped, the prediction is handed over first; separate, the labeller waits for it (up to a bound generous
    for a loaded machine) and counts the frames it labelled without one: only the first, which has none."""
    source = tmp_path / "gapped.c3d"
    gapped_slice(data_dir, source)
    path = tmp_path / "fb.yaml"
    placing = ", group: frame" if layout == "grouped" else ""
    path.write_text(
        "name: fb\nnodes:\n"
        f"  tracker: {{plugin: c3d-replay, config: {{path: '{source}', unlabelled: true, speed: 10}}}}\n"
        "  labeller: {plugin: labeller, inputs: {markers: tracker/markers, predictions: filler/predictions},"
        f" wait_for: {{predictions: 2000}}{placing}}}\n"
        f"  filler: {{plugin: occlusion-filler, inputs: {{markers: labeller/markers}}{placing}}}\n"
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
    reference = offline(source, wire=layout == "separate")
    stats = orjson.loads((tmp_path / "s.json").read_bytes())["labeller"]
    assert stats["unpaired"] == (0 if layout == "grouped" else 1), stats
    assert len(reference) == FRAMES and len(live) == len(reference)
    assert [m["frame"] for m in live] == [m["frame"] for m in reference]
    assert live == reference  # labels, positions and rays of every frame
    assert len(reference[-1]["labels"]) > 10  # it did label the capture
    # and the predictions did count: without them the same capture is labelled otherwise
    assert sum(a != b for a, b in zip(offline(source, feedback=False), reference, strict=True)) > FRAMES // 10
