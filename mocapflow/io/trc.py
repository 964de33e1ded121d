"""TRC marker files (Motion Analysis track-row-column text, the marker format of OpenSim).

Layout: a ``PathFileType`` line; a line of header keys (DataRate, CameraRate, NumFrames, NumMarkers, Units,
OrigDataRate, OrigDataStartFrame, OrigNumFrames...) and a line of their values; a ``Frame#  Time  name...`` line
with each marker name above its X column; an ``X1 Y1 Z1...`` line; then one tab-separated line per frame, where an
empty cell is a missing coordinate. Files spaced throughout are read too, and so are spaced frame lines under a tabbed
header (some exporters write both). TRC has no per-sample flags, so a TRC file reads back observed wherever a
position exists, and ``extra`` points are written as further markers (OpenSim shows them as virtual markers).
"""

from __future__ import annotations

from pathlib import Path
from typing import Final

import numpy as np

from mocapflow.errors import MocapFileError
from mocapflow.io.markerdata import (
    FLAG_MISSING,
    FLAG_OBSERVED,
    MarkerData,
    clean_labels,
    missing_as_nan,
    unit_scale,
)

SIGNATURE: Final = "PathFileType"
HEADER_KEYS: Final = (
    "DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units", "OrigDataRate", "OrigDataStartFrame", "OrigNumFrames",
)
FIRST_DATA_LINE: Final = 5


def is_trc(path: Path) -> bool:
    """Whether the file starts like a TRC file (its first word is PathFileType); False if it cannot be read."""
    try:
        with path.open("rb") as stream:
            head = stream.read(len(SIGNATURE) + 3)
    except OSError:
        return False
    return head.removeprefix(b"\xef\xbb\xbf").startswith(SIGNATURE.encode())


def _number(text: str | None, kind: type[float | int] = float) -> float | int | None:
    """A header value as a number, or None when it is absent or not a (finite, for int) number."""
    try:
        return kind(float(text)) if text is not None else None
    except (ValueError, OverflowError):
        return None


def read_trc(path: str | Path, *, strip_prefix: bool = True) -> MarkerData:
    """Read the marker trajectories of a TRC file in mm (empty cells, NaN or 0,0,0 are missing)."""
    path = Path(path)
    if not path.is_file():
        raise MocapFileError(f"{path}: no such file")
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").removeprefix("\ufeff").splitlines()
    except OSError as exc:
        raise MocapFileError(f"{path}: cannot read ({' '.join(str(exc).split())})") from exc
    if not lines or not lines[0].startswith(SIGNATURE):
        raise MocapFileError(f"{path}: not a TRC file (it does not start with {SIGNATURE})")
    if len(lines) < FIRST_DATA_LINE or not lines[3].lstrip().startswith("Frame#"):
        raise MocapFileError(f"{path}: truncated or malformed TRC header (no Frame# line)")
    tabbed = "\t" in lines[3]
    split = (lambda line: line.split("\t")) if tabbed else str.split
    pairs = zip(split(lines[1]), split(lines[2]), strict=False)
    header = {key.strip(): value.strip() for key, value in pairs if key.strip()}

    n_coordinates = sum(1 for cell in split(lines[4]) if cell.strip())
    n_markers = n_coordinates // 3 or int(_number(header.get("NumMarkers"), int) or 0)
    if n_markers == 0:
        raise MocapFileError(f"{path}: the TRC file holds no markers")
    name_cells = split(lines[3])[2:]
    names = name_cells[::3] if tabbed else [cell for cell in name_cells if cell.strip()]
    names = (names + [""] * n_markers)[:n_markers]

    # a data line without tabs is split at spaces (some exporters write a tabbed header over spaced rows)
    rows = [line.split("\t") if "\t" in line else line.split() for line in lines[FIRST_DATA_LINE:] if line.strip()]
    if not rows:
        raise MocapFileError(f"{path}: the TRC file holds no frames")
    declared = _number(header.get("NumFrames"), int)
    if declared is not None and len(rows) < declared:
        raise MocapFileError(f"{path}: truncated TRC file ({len(rows)} frames, NumFrames says {declared})")
    values = _cells_to_floats(rows, 2 + 3 * n_markers, path)

    rate = _rate(header, values[:, 1])
    if rate is None:
        raise MocapFileError(f"{path}: the TRC file gives no DataRate and no usable Time column")
    positions = values[:, 2:].reshape(len(rows), n_markers, 3) * unit_scale(header.get("Units", ""), path)
    missing_as_nan(positions)
    first = values[0, 0]
    first_frame = int(first) if np.isfinite(first) else int(_number(header.get("OrigDataStartFrame"), int) or 1)
    present = np.isfinite(positions[..., 0])
    return MarkerData(
        positions=positions,
        labels=clean_labels(names, strip_prefix),
        rate=rate,
        first_frame=max(first_frame, 0),
        flags=np.where(present, FLAG_OBSERVED, FLAG_MISSING).astype(np.uint8),
    )


def _cells_to_floats(rows: list[list[str]], width: int, path: Path) -> np.ndarray:
    """(rows, width) floats; an empty cell, or one past the end of a short row, is NaN. A cell that is no number
    raises ``MocapFileError`` naming its frame row and column."""
    values = np.full((len(rows), width), np.nan)
    for index, cells in enumerate(rows):
        cells = cells[:width]
        try:
            values[index, : len(cells)] = [float(cell) if cell.strip() else np.nan for cell in cells]
        except ValueError:
            column, cell = next((c, cell) for c, cell in enumerate(cells) if cell.strip() and not _is_number(cell))
            shown = cell.strip() if len(cell.strip()) <= 40 else cell.strip()[:40] + "..."
            raise MocapFileError(f"{path}: not a number in the TRC data, frame row {index + 1}, column {column + 1}: "
                                 f"{shown!r}") from None
    return values


def _is_number(cell: str) -> bool:
    """Whether a cell reads as a number."""
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _rate(header: dict[str, str], times: np.ndarray) -> float | None:
    """DataRate, else CameraRate, else the rate of the Time column."""
    for key in ("DataRate", "CameraRate"):
        rate = _number(header.get(key))
        if rate is not None and rate > 0:
            return float(rate)
    steps = np.diff(times[np.isfinite(times)])
    step = float(np.median(steps)) if steps.size else 0.0
    return 1.0 / step if step > 0 else None


def write_trc(path: str | Path, data: MarkerData) -> None:
    """Write markers then ``extra`` points as a TRC file in mm, with empty cells where a sample is missing."""
    path = Path(path)
    names = list(data.labels) + list(data.extra)
    bad = [name for name in names if any(char in name for char in "\t\r\n")]
    if bad:
        raise ValueError(f"TRC labels cannot hold tabs or line breaks: {bad}")
    positions = np.concatenate([data.positions, *(p[:, None] for p in data.extra.values())], axis=1)
    n_frames, n_points = positions.shape[:2]
    positions = np.where(np.isfinite(positions).all(axis=2, keepdims=True), positions, np.nan)
    frames = np.arange(n_frames)
    table = np.column_stack([frames + data.first_frame, frames / data.rate, positions.reshape(n_frames, -1)])

    rate = f"{data.rate:.10g}"
    header = [
        f"{SIGNATURE}\t4\t(X/Y/Z)\t{path.name}",
        "\t".join(HEADER_KEYS),
        "\t".join([rate, rate, str(n_frames), str(n_points), "mm", rate, str(data.first_frame), str(n_frames)]),
        "\t".join(["Frame#", "Time", *(f"{name}\t\t" for name in names)]),
        "\t\t" + "\t".join(f"X{i}\tY{i}\tZ{i}" for i in range(1, n_points + 1)),
        "",
    ]
    row_format = "%d\t%.10g\t" + "\t".join(["%.9g"] * 3 * n_points)
    body = [(row_format % tuple(row)).replace("nan", "") for row in table.tolist()]
    try:
        path.write_text("\n".join(header + body) + "\n", encoding="utf-8")
    except OSError as exc:
        raise MocapFileError(f"{path}: cannot write ({' '.join(str(exc).split())})") from exc
