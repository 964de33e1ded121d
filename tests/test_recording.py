"""Record a live run to MCAP, replay it, record the replay: same messages, same order, same timing."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import CLI, graph_file

from mocapflow.errors import MocapFileError
from mocapflow.io.recording import RecordedSample, RecordingWriter, read_recording
from mocapflow.runtime.session import open_router

pytestmark = pytest.mark.integration  # every test here starts processes and Zenoh sessions



def wait_for_line(proc: subprocess.Popen[str], text: str) -> None:
    for line in proc.stdout:
        if text in line:
            return
    raise AssertionError(f"never printed {text!r}")


def test_replay_reproduces_a_live_run(tmp_path: Path, free_endpoint: str) -> None:
    graph, prefix = graph_file(tmp_path, "rec", free_endpoint, """
  tracker: {plugin: simulator, config: {rig: rods, rate: 240, frames: 720, dropout_rate: 2}}
  relay: {plugin: relay, inputs: {markers: tracker/markers}}
""")
    live = tmp_path / "live.mcap"
    rec = subprocess.Popen([*CLI, "record", f"{prefix}/*/markers", "-o", str(live), "--connect",
                            free_endpoint, "--duration", "60"], stdout=subprocess.PIPE, text=True)
    run = subprocess.Popen([*CLI, "run", str(graph)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    wait_for_line(rec, "recording")
    out, _ = run.communicate(timeout=60)
    assert run.returncode == 0, out
    time.sleep(0.5)
    rec.terminate()
    rec.communicate(timeout=10)
    original = list(read_recording(live))
    assert sum(not s.delete for s in original) == 2 * 720

    # replay into a fresh router while recording again
    with open_router([free_endpoint]):
        again = tmp_path / "again.mcap"
        rec2 = subprocess.Popen([*CLI, "record", f"{prefix}/**", "-o", str(again), "--connect",
                                 free_endpoint], stdout=subprocess.PIPE, text=True)
        wait_for_line(rec2, "recording")
        time.sleep(0.5)
        replay = subprocess.run([*CLI, "replay", str(live), "--connect", free_endpoint], capture_output=True,
                                text=True, timeout=60)
        assert replay.returncode == 0, replay.stderr
        assert f"replayed {len(original)} samples" in replay.stdout
        time.sleep(0.5)
        rec2.terminate()
        rec2.communicate(timeout=10)
    replayed = list(read_recording(again))
    assert [(s.key, s.encoding, s.payload, s.delete) for s in replayed] == \
           [(s.key, s.encoding, s.payload, s.delete) for s in original]
    # every sample again, in its order; how closely the replay keeps the original timing is a figure the replay
    # prints (p95 lateness), not something a busy machine should fail a build on
    t1 = np.array([s.log_time_ns for s in replayed], dtype=np.int64)
    assert (np.diff(t1) >= 0).all()
    assert "p95 " in replay.stdout


def test_recording_round_trip_and_bad_files(tmp_path: Path) -> None:
    path = tmp_path / "x.mcap"
    samples = [RecordedSample("a/b", "application/json;mocapflow/MarkerFrame", b'{"x":1}', 10),
               RecordedSample("a/c", "text/plain", b"hello", 20), RecordedSample("a/b", "zenoh/bytes", b"", 30, True)]
    with RecordingWriter(path) as writer:
        for s in samples:
            writer.write(s)
    assert list(read_recording(path)) == samples
    not_mcap = tmp_path / "n.mcap"
    not_mcap.write_text("hello")
    with pytest.raises(MocapFileError, match="not an MCAP recording"):
        list(read_recording(not_mcap))
    with pytest.raises(MocapFileError, match="no such file"):
        list(read_recording(tmp_path / "missing.mcap"))
    # a recording cut short (its writer killed) reads up to the cut: a prefix of what was written, never an error
    truncated = tmp_path / "t.mcap"
    truncated.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    recovered = list(read_recording(truncated))
    assert recovered == samples[: len(recovered)]
