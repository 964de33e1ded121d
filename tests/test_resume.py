"""A node's state kept for its restarts: written by a thread of its own, the latest state kept whole, removed at the
end, and a folder that cannot be written costs the stream nothing."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import pytest

from mocapflow.runtime.resume import StateKeeper, state_path


def _kept(keeper: StateKeeper, want: int) -> object:
    """What a restarted node would load, once the writer has caught up with the state numbered ``want``."""
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        state = keeper.load()
        if state is not None and state["n"] == want:
            return state
        time.sleep(0.01)
    return keeper.load()


def test_the_latest_state_is_kept_whole_and_removed_at_the_end(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    keeper = StateKeeper("run1", "labeller")
    assert keeper.load() is None
    big = np.arange(200_000.0)
    for n in range(50):  # saved faster than written: the ones waiting are replaced, never written half
        keeper.save({"n": n, "tracks": big + n})
    kept = _kept(StateKeeper("run1", "labeller"), 49)  # as the restarted node reads it
    assert isinstance(kept, dict) and kept["n"] == 49 and np.array_equal(kept["tracks"], big + 49)
    assert (state_path("run1", "labeller").parent.parent.stat().st_mode & 0o777) == 0o700
    keeper.save({"n": 50, "tracks": big})
    keeper.clear()  # the write under way ends first, then the state goes
    assert not state_path("run1", "labeller").exists()
    assert list(state_path("run1", "labeller").parent.iterdir()) == []
    assert StateKeeper("run2", "labeller").load() is None  # another run starts afresh


def test_nothing_is_kept_outside_a_launched_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    keeper = StateKeeper("", "labeller")
    keeper.save({"n": 1})
    keeper.clear()
    assert keeper.load() is None and list(tmp_path.iterdir()) == []


def test_a_folder_that_cannot_be_written_is_said_once_and_costs_the_stream_nothing(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(blocker))
    keeper = StateKeeper("run1", "labeller")
    with caplog.at_level(logging.WARNING, logger="mocapflow.worker"):
        for n in range(3):
            keeper.save({"n": n})  # returns at once; the writer meets the error
            time.sleep(0.05)
        keeper.clear()
    assert keeper.load() is None
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "cannot keep the state for a restart" in warnings[0], warnings
