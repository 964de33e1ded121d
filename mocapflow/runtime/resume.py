"""State a node keeps across its own restarts within one run (a labeller's tracks), in a folder only this user
reaches: ``$XDG_RUNTIME_DIR`` (else the temporary folder) ``/mocapflow-UID/RUN/NODE.state``.

A node keeps what it would need to carry on (atomically: write, then rename, so a kill never leaves half a state)
and loads it when it starts again in the same run; a new run, with another run id, starts afresh. The file is Python's
pickle format, so it is read only from that private folder and only by the user who wrote it.

The frame path pays only for the copy (:class:`StateKeeper`: the state pickled, 0.6 ms for the labeller of a simulated
human, 52 markers, at 240 Hz); a thread of the process writes and renames the file, which on the frame path made a save
cost 2.6 ms (median of 20; up to 7 ms on a disk-backed temporary folder), twice a second.
"""

from __future__ import annotations

import contextlib
import logging
import os
import pickle
import tempfile
import threading
from pathlib import Path
from typing import Any

log = logging.getLogger("mocapflow.worker")


def state_path(run: str, node: str) -> Path:
    base = Path(os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir()) / f"mocapflow-{os.getuid()}"
    return base / run / f"{node}.state"


class StateKeeper:
    """Keeps the latest state of ``node`` in ``run`` for its restarts (nothing is kept outside a launched run).

    ``save`` pickles the state at once, so what is kept is the state of that moment, and hands the bytes to a writer
    thread; a state saved while an earlier one is still being written replaces the one waiting, so the writer never
    falls behind the frames. ``clear`` waits for the write under way, then removes the file, once the node has
    finished for good."""

    def __init__(self, run: str, node: str) -> None:
        self._path = state_path(run, node) if run else None
        self._waiting: bytes | None = None
        self._done = False
        self._wake = threading.Condition()
        self._writer: threading.Thread | None = None
        self._failed = False  # said once: the stream goes on, each later save fails alike

    def load(self) -> Any | None:
        """What the node kept in this run before it restarted, or None."""
        path = self._path
        if path is None or not path.is_file() or path.stat().st_uid != os.getuid():
            return None
        with path.open("rb") as f:
            return pickle.load(f)  # noqa: S301 - written by this user into a folder only this user reaches

    def save(self, state: Any) -> None:
        if self._path is None:
            return
        data = pickle.dumps(state, protocol=pickle.HIGHEST_PROTOCOL)
        with self._wake:
            self._waiting = data
            self._wake.notify()
        if self._writer is None:
            self._writer = threading.Thread(target=self._write, name=f"state {self._path.stem}", daemon=True)
            self._writer.start()

    def clear(self) -> None:
        if self._writer is not None:
            with self._wake:
                self._done = True
                self._wake.notify()
            self._writer.join()
        if self._path is not None:
            # none was written where the folder cannot be; a state left behind is read only by a restart in this run
            with contextlib.suppress(OSError):
                self._path.unlink(missing_ok=True)

    def _write(self) -> None:
        assert self._path is not None
        part = self._path.with_name(self._path.name + ".part")
        while True:
            with self._wake:
                while self._waiting is None and not self._done:
                    self._wake.wait()
                data, self._waiting = self._waiting, None
            if data is None:  # finished, and nothing left to write
                return
            try:
                self._path.parent.mkdir(parents=True, exist_ok=True)
                self._path.parent.parent.chmod(0o700)
                part.write_bytes(data)
                part.replace(self._path)
            except OSError as exc:  # the stream goes on; a restart then resumes from an older state, or afresh
                if not self._failed:
                    log.warning("%s: cannot keep the state for a restart: %s", self._path, exc.strerror or exc)
                self._failed = True
