"""Reading and writing marker files as C3D or TRC, chosen by file content or extension, and choosing markers or
joining trials. The data type itself is ``markerdata.MarkerData``."""

from __future__ import annotations

from collections.abc import Sequence
from fnmatch import fnmatchcase
from pathlib import Path

import numpy as np

from mocapflow.errors import MocapFileError
from mocapflow.io.c3d import is_c3d, read_c3d, write_c3d
from mocapflow.io.markerdata import FLAG_ESTIMATED, FLAG_MAX, FLAG_MISSING, FLAG_OBSERVED, MarkerData
from mocapflow.io.trc import is_trc, read_trc, write_trc

__all__ = ["FLAG_ESTIMATED", "FLAG_MAX", "FLAG_MISSING", "FLAG_OBSERVED", "MarkerData", "join_trials", "read_markers",
           "select_markers", "write_markers"]


def read_markers(path: str | Path, *, strip_prefix: bool = True) -> MarkerData:
    """Read a C3D or TRC file, recognised by its first bytes, else by its extension."""
    path = Path(path)
    if not path.is_file():
        raise MocapFileError(f"{path}: no such file")
    if is_c3d(path):
        return read_c3d(path, strip_prefix=strip_prefix)
    if is_trc(path):
        return read_trc(path, strip_prefix=strip_prefix)
    suffix = path.suffix.lower()
    if suffix == ".c3d":
        return read_c3d(path, strip_prefix=strip_prefix)
    if suffix == ".trc":
        return read_trc(path, strip_prefix=strip_prefix)
    raise MocapFileError(f"{path}: neither a C3D nor a TRC marker file")


def select_markers(data: MarkerData, include: Sequence[str] = (), exclude: Sequence[str] = ()) -> MarkerData:
    """The markers whose labels match one of the shell-style ``include`` patterns (all when none is given) and
    none of the ``exclude`` ones. A pattern that matches no label, or a choice that leaves no marker, is an error
    naming it (a mistyped pattern must not pass unnoticed)."""
    for pattern in [*include, *exclude]:
        if not any(fnmatchcase(label, pattern) for label in data.labels):
            raise MocapFileError(f"no marker label matches {pattern!r} (labels: {', '.join(data.labels[:12])}"
                                 f"{'...' if len(data.labels) > 12 else ''})")
    keep = [i for i, label in enumerate(data.labels)
            if (not include or any(fnmatchcase(label, p) for p in include))
            and not any(fnmatchcase(label, p) for p in exclude)]
    if not keep:
        raise MocapFileError("the marker choice leaves no marker")
    return MarkerData(positions=data.positions[:, keep], labels=[data.labels[i] for i in keep], rate=data.rate,
                      first_frame=data.first_frame, flags=None if data.flags is None else data.flags[:, keep],
                      extra=data.extra)


def join_trials(trials: Sequence[MarkerData]) -> MarkerData:
    """Several trials of one subject as one recording: frames one after the other, markers matched by label (a
    marker absent from a trial is missing there), at the first trial's rate."""
    if len(trials) == 1:
        return trials[0]
    labels = list(dict.fromkeys(label for trial in trials for label in trial.labels))
    column = {label: i for i, label in enumerate(labels)}
    blocks = []
    for trial in trials:
        block = np.full((trial.n_frames, len(labels), 3), np.nan)
        block[:, [column[label] for label in trial.labels]] = trial.positions
        blocks.append(block)
    return MarkerData(positions=np.concatenate(blocks), labels=labels, rate=trials[0].rate)


def write_markers(path: str | Path, data: MarkerData) -> None:
    """Write ``data`` as C3D or TRC, chosen by the extension of ``path``."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".c3d":
        write_c3d(path, data)
    elif suffix == ".trc":
        write_trc(path, data)
    else:
        raise MocapFileError(f"{path}: unknown marker file extension {suffix!r} (expected .c3d or .trc)")
