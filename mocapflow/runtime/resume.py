"""State a node keeps across its own restarts within one run (a labeller's tracks), in a folder only this user
reaches: ``$XDG_RUNTIME_DIR`` (else the temporary folder) ``/mocapflow-UID/RUN/NODE.state``.

A node saves what it would need to carry on (atomically: write, then rename, so a kill never leaves half a state)
and loads it when it starts again in the same run; a new run, with another run id, starts afresh. The file is Python's
pickle format, so it is read only from that private folder and only by the user who wrote it.
"""

from __future__ import annotations

import os
import pickle
import tempfile
from pathlib import Path
from typing import Any


def state_path(run: str, node: str) -> Path:
    base = Path(os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir()) / f"mocapflow-{os.getuid()}"
    return base / run / f"{node}.state"


def save_state(run: str, node: str, state: Any) -> None:
    """Keep ``state`` for a restart of ``node`` in ``run`` (nothing is kept outside a launched run)."""
    if not run:
        return
    path = state_path(run, node)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.parent.parent.chmod(0o700)
    part = path.with_name(path.name + ".part")
    with part.open("wb") as f:
        pickle.dump(state, f, protocol=pickle.HIGHEST_PROTOCOL)
    part.replace(path)


def load_state(run: str, node: str) -> Any | None:
    """What ``node`` kept in ``run`` before it restarted, or None."""
    path = state_path(run, node) if run else None
    if path is None or not path.is_file() or path.stat().st_uid != os.getuid():
        return None
    with path.open("rb") as f:
        return pickle.load(f)  # noqa: S301 - written by this user into a folder only this user reaches


def clear_state(run: str, node: str) -> None:
    """Forget the state once the node has finished for good."""
    if run:
        state_path(run, node).unlink(missing_ok=True)
