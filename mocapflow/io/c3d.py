"""C3D marker files, read and written through ezc3d; each file is checked first so no malformed one reaches its parser.

Sample flags in a written file. The fourth word of every point sample follows the C3D convention that every reader
understands: negative = invalid (missing), 0 = computed rather than measured (estimated), > 0 = measured
(observed). A measured sample is written with residual byte 1 and camera byte 1, because ezc3d 1.7 packs these two
bytes of floating-point files the opposite way round from the C3D specification (pyomeca/ezc3d#386): only a word
whose two bytes are equal reads the same in ezc3d and in readers that follow the specification (the ``c3d``
package, Vicon, Mokka). For that same reason the camera byte cannot carry the estimation case (flag codes 2..15)
portably, and one parameter per sample would break the 32 KB size limit of a C3D parameter. The case is therefore
kept in the parameter group MOCAPFLOW: FLAG_RUNS holds (code, count) pairs, the run lengths of the codes of the
computed samples taken marker by marker, frame by frame, continued in FLAG_RUNS2, FLAG_RUNS3... past 255 runs (as
POINT:LABELS2 continues POINT:LABELS). A gap is filled by one case, so a recording needs about one run per gap.
Other software ignores the group; ``read_c3d`` uses the runs only while their total matches the file's computed
samples, so a file edited elsewhere reads back with FLAG_ESTIMATED. MOCAPFLOW:EXTRA_USED counts the trailing points
that are ``extra`` points rather than markers.

In files from other software, residual 0 means "computed" only when the file records residuals at all: many
exporters (CMU, processed Vicon trials) write 0 for every valid sample, and those samples are taken as observed.
"""

from __future__ import annotations

import logging
import math
import os
import warnings
from pathlib import Path
from typing import Any, Final

import ezc3d
import numpy as np

from mocapflow.errors import MocapFileError
from mocapflow.io.markerdata import (
    FLAG_ESTIMATED,
    FLAG_MAX,
    FLAG_MISSING,
    FLAG_OBSERVED,
    MarkerData,
    clean_labels,
    missing_as_nan,
    unit_scale,
)

C3D_KEY: Final = 0x50
"""Second byte of every C3D file."""
BLOCK: Final = 512
MAX_PARAMETER_BLOCKS: Final = 255
PROCESSORS: Final = {84: "<", 85: "<", 86: ">"}
"""Processor type byte of the parameter section (Intel, DEC, MIPS) -> byte order of its integers."""
log = logging.getLogger(__name__)

MODEL_OUTPUTS: Final = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS")
"""POINT parameters listing points that hold model outputs (degrees, newtons...) rather than positions."""
GROUP: Final = "MOCAPFLOW"
RUNS_PER_PARAMETER: Final = 255
"""A parameter dimension is one byte."""
MAX_RUN_PARAMETERS: Final = 40
"""FLAG_RUNS parameters at most (80 KB), so the parameter section stays within its 255 blocks."""
MAX_RUN: Final = 2**24
"""Largest count a float32 holds exactly."""
OBSERVED_WORD_BYTE: Final = 1
PARAMETER_INT: Final = ezc3d.ezc3d.INT
PARAMETER_FLOAT: Final = ezc3d.ezc3d.FLOAT


def is_c3d(path: Path) -> bool:
    """Whether the file starts like a C3D file (its second byte is 0x50); False if it cannot be read."""
    try:
        with path.open("rb") as stream:
            head = stream.read(2)
    except OSError:
        return False
    return len(head) == 2 and head[1] == C3D_KEY


def _check_layout(path: Path) -> tuple[int, int]:
    """Check the header and parameter records against the file before ezc3d sees it: (first frame, frame count).

    ezc3d reads a truncated file silently (fewer frames), trusts every size the file declares and crashes on a file
    with no 3D points, so those are checked here.
    """
    try:
        size = path.stat().st_size
        with path.open("rb") as stream:
            head = stream.read(BLOCK)
            parameter_block = head[0] if head else 0
            stream.seek(max(parameter_block - 1, 0) * BLOCK)
            parameter_head = stream.read(4)
    except OSError as exc:
        raise MocapFileError(f"{path}: cannot read ({_one_line(exc)})") from exc
    if len(head) < BLOCK or head[1] != C3D_KEY:
        raise MocapFileError(f"{path}: not a C3D file (no C3D header)")
    if parameter_block < 2 or len(parameter_head) < 4:
        raise MocapFileError(f"{path}: truncated or corrupt C3D file (parameter section out of the file)")
    if parameter_head[3] not in PROCESSORS:
        raise MocapFileError(f"{path}: corrupt C3D file (unknown processor type {parameter_head[3]})")
    byte_order = PROCESSORS[parameter_head[3]]
    words = np.frombuffer(head[2:20], dtype=f"{byte_order}u2").astype(np.int64)
    n_points, n_analog, first, last, data_start = words[0], words[1], words[2], words[3], words[7]
    if (parameter_block - 1 + parameter_head[2]) * BLOCK > size:
        raise MocapFileError(f"{path}: truncated C3D file (parameter section cut short)")
    # Sign of POINT:SCALE (negative = float data): the byte holding the float's sign bit in each processor format.
    sign_byte = {84: 15, 85: 13, 86: 12}[parameter_head[3]]
    word_bytes = 4 if head[sign_byte] & 0x80 else 2
    n_frames = last - first + 1 if last >= first else 0
    expected = (data_start - 1) * BLOCK + n_frames * (4 * n_points + n_analog) * word_bytes
    if data_start < 2:
        raise MocapFileError(f"{path}: corrupt C3D header (data start block {data_start})")
    if size < expected:
        raise MocapFileError(f"{path}: truncated C3D file ({size} bytes, the header announces {expected})")
    if n_points == 0:  # ezc3d 1.7 crashes (segfault) on a file of analog channels only
        raise MocapFileError(f"{path}: the C3D file holds no 3D points")
    with path.open("rb") as stream:
        stream.seek((parameter_block - 1) * BLOCK)
        section = stream.read(MAX_PARAMETER_BLOCKS * BLOCK)
    problem = _parameter_problem(section, byte_order)
    if problem:
        raise MocapFileError(f"{path}: corrupt C3D parameter section ({problem})")
    return int(first), int(n_frames)


def _parameter_problem(section: bytes, byte_order: str) -> str | None:
    """Walk the parameter records as ezc3d will and say what is wrong, if anything.

    ezc3d trusts each record: a parameter whose dimensions promise more data than its record holds makes it read
    for minutes, and a record with group id 0 makes it index outside its group list.
    """
    position = 4
    while True:
        if position + 2 > len(section):
            return "records run past the end of the section"
        name_length = abs(int.from_bytes(section[position : position + 1], "little", signed=True))
        if name_length == 0:
            return None
        group = int.from_bytes(section[position + 1 : position + 2], "little", signed=True)
        if group == 0:
            return f"record at byte {position} belongs to group 0"
        cursor = position + 2 + name_length
        offset = int.from_bytes(section[cursor : cursor + 2], "big" if byte_order == ">" else "little")
        cursor += 2
        if group > 0:
            kind = int.from_bytes(section[cursor : cursor + 1], "little", signed=True)
            if kind not in (-1, 1, 2, 4):
                return f"record at byte {position} has unknown type {kind}"
            n_dims = section[cursor + 1] if cursor + 1 < len(section) else 0
            dims = section[cursor + 2 : cursor + 2 + n_dims]
            cursor += 2 + n_dims + math.prod(dims) * abs(kind)
        end = cursor + 1 + (section[cursor] if cursor < len(section) else 0)
        if end > len(section):
            return f"record at byte {position} runs past the end of the section"
        if offset == 0:
            return None
        if position + 2 + name_length + offset != end:
            return f"record at byte {position} does not end where its offset says"
        position = end


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


def _values(group: Any, name: str) -> list:
    """Values of parameter ``name`` and of its continuations ``name2``, ``name3``... as one list."""
    values: list = []
    suffix = ""
    while name + suffix in group:
        value = group[name + suffix]["value"]
        values.extend(value.ravel(order="F").tolist() if isinstance(value, np.ndarray) else value)
        suffix = str(int(suffix or 1) + 1)
    return values


def _frame_number(parameters: Any, header_first: int) -> int:
    """First frame number: TRIAL:ACTUAL_START_FIELD (two 16-bit words, for numbers past 65535), else the header."""
    words = _values(parameters["TRIAL"], "ACTUAL_START_FIELD") if "TRIAL" in parameters else []
    if len(words) >= 2:
        return (int(words[0]) & 0xFFFF) | (int(words[1]) & 0xFFFF) << 16
    return header_first


def read_c3d(path: str | Path, *, strip_prefix: bool = True) -> MarkerData:
    """Read the marker trajectories of a C3D file in mm; analog data and model outputs (angles...) are skipped."""
    path = Path(path)
    if not path.is_file():
        raise MocapFileError(f"{path}: no such file")
    header_first, header_frames = _check_layout(path)
    try:
        c3d = ezc3d.c3d(str(path))
    except Exception as exc:  # ezc3d raises bare RuntimeError/OSError/IndexError on malformed content
        raise MocapFileError(f"{path}: unreadable C3D file ({_one_line(exc)})") from exc
    parameters = c3d["parameters"]
    point = parameters["POINT"]
    points = c3d["data"]["points"]
    n_points, n_frames = points.shape[1], points.shape[2]
    if n_points == 0:
        raise MocapFileError(f"{path}: the C3D file holds no 3D points")
    if n_frames == 0:
        raise MocapFileError(f"{path}: the C3D file holds no frames")
    if n_frames < header_frames:
        raise MocapFileError(f"{path}: corrupt C3D file ({n_frames} frames read, the header announces {header_frames})")
    rates = _values(point, "RATE")
    rate = float(rates[0]) if rates else float(c3d["header"]["points"]["frame_rate"])
    if not rate > 0:
        raise MocapFileError(f"{path}: the C3D file has no point rate")
    units = _values(point, "UNITS")
    scale = unit_scale(units[0] if units else "", path)
    raw_labels = [str(label) for label in _values(point, "LABELS")][:n_points]
    raw_labels += [""] * (n_points - len(raw_labels))

    ours = GROUP in parameters
    extra_used = _values(parameters[GROUP], "EXTRA_USED") if ours else []
    n_extra = min(max(int(extra_used[0]), 0), n_points) if extra_used else 0
    outputs = {str(label).strip() for name in MODEL_OUTPUTS for label in _values(point, name)}
    markers = [i for i in range(n_points - n_extra) if raw_labels[i].strip() not in outputs]
    if len(markers) < n_points - n_extra:
        log.info("%s: %d model outputs of POINT (%s) are not markers: skipped", path.name,
                 n_points - n_extra - len(markers), ", ".join(n for n in MODEL_OUTPUTS if _values(point, n)))

    positions = np.ascontiguousarray(points[:3].transpose(2, 1, 0))
    positions *= scale
    residuals = c3d["data"]["meta_points"]["residuals"][0].T
    positions[residuals < 0] = np.nan
    missing_as_nan(positions)
    marker_positions = positions[:, markers]
    marker_residuals = residuals[:, markers]
    runs = _read_runs(parameters[GROUP]) if ours else None
    flags = _decode_flags(marker_residuals, np.isfinite(marker_positions[..., 0]), runs, ours)
    extra_names = clean_labels(raw_labels[n_points - n_extra :], strip_prefix=False)
    extra = {name: positions[:, n_points - n_extra + i] for i, name in enumerate(extra_names)}
    return MarkerData(
        positions=marker_positions,
        labels=clean_labels([raw_labels[i] for i in markers], strip_prefix, taken=extra_names),
        rate=rate,
        first_frame=_frame_number(parameters, header_first),
        flags=flags,
        extra=extra,
    )


def _read_runs(group: Any) -> np.ndarray | None:
    values = _values(group, "FLAG_RUNS")
    if not values or len(values) % 2:
        return None
    runs = np.asarray(values, dtype=np.int64).reshape(-1, 2).T
    valid = (runs[0] >= FLAG_ESTIMATED).all() and (runs[0] <= FLAG_MAX).all() and (runs[1] >= 0).all()
    return runs if valid else None


def _decode_flags(residuals: np.ndarray, present: np.ndarray, runs: np.ndarray | None, ours: bool) -> np.ndarray:
    """Flags from the residual convention (see the module docstring) and the estimation-case runs if they fit."""
    flags = np.where(present, FLAG_OBSERVED, FLAG_MISSING).astype(np.uint8)
    if not (ours or (residuals[present] > 0).any()):
        return flags
    computed = present & (residuals == 0)
    flags[computed] = FLAG_ESTIMATED
    if runs is not None and runs[1].sum() == computed.sum():
        flags.T[computed.T] = np.repeat(runs[0], runs[1])
    return flags


def _encode_runs(codes: np.ndarray) -> np.ndarray:
    """(code, count) run lengths of ``codes``, (2, R) float; runs longer than a float32 holds exactly are split."""
    starts = np.r_[0, np.flatnonzero(np.diff(codes)) + 1]
    lengths = np.diff(np.r_[starts, codes.size])
    pieces = -(-lengths // MAX_RUN)
    counts = np.full(pieces.sum(), MAX_RUN, dtype=np.int64)
    counts[np.cumsum(pieces) - 1] = lengths - (pieces - 1) * MAX_RUN
    return np.vstack([np.repeat(codes[starts], pieces), counts]).astype(np.float64)


def _parameter(value: np.ndarray, kind: int, description: str) -> dict[str, Any]:
    return {"type": kind, "description": description, "is_locked": False, "value": value}


def write_c3d(path: str | Path, data: MarkerData) -> None:
    """Write markers then ``extra`` points as a floating-point C3D file in mm, flags as described in the module."""
    path = Path(path)
    flags = data.sample_flags()
    names = list(data.labels) + list(data.extra)
    positions = np.concatenate([data.positions, *(p[:, None] for p in data.extra.values())], axis=1)
    n_frames, n_points = positions.shape[:2]
    extra_present = np.isfinite(positions[:, data.n_markers :]).all(axis=2)

    residuals = np.concatenate([
        np.select([flags == FLAG_OBSERVED, flags >= FLAG_ESTIMATED], [OBSERVED_WORD_BYTE, 0], -1),
        np.where(extra_present, 0, -1),
    ], axis=1).astype(np.float64)
    masks = np.zeros((7, n_points, n_frames), dtype=bool)
    masks[0] = (residuals == OBSERVED_WORD_BYTE).T
    xyz1 = np.ones((4, n_points, n_frames))
    xyz1[:3] = np.nan_to_num(positions, nan=0.0).transpose(2, 1, 0)

    c3d = ezc3d.c3d()
    point = c3d["parameters"]["POINT"]
    point["RATE"]["value"] = np.array([float(data.rate)])
    point["UNITS"]["value"] = ["mm"]
    point["LABELS"]["value"] = names
    c3d["data"]["points"] = xyz1
    c3d["data"]["meta_points"] = {"residuals": residuals.T[None], "camera_masks": masks}
    first = data.first_frame
    c3d["header"]["points"]["first_frame"] = min(max(first, 1), 0xFFFF) - 1
    last = first + n_frames - 1
    c3d["parameters"]["TRIAL"] = {
        "__METADATA__": {"DESCRIPTION": "Trial information", "IS_LOCKED": False},
        "ACTUAL_START_FIELD": _parameter(_words(first), PARAMETER_INT, "first frame number (low, high 16-bit word)"),
        "ACTUAL_END_FIELD": _parameter(_words(last), PARAMETER_INT, "last frame number (low, high 16-bit word)"),
    }
    group: dict[str, Any] = {
        "__METADATA__": {"DESCRIPTION": "mocapflow sample flags and extra points", "IS_LOCKED": False},
        "EXTRA_USED": _parameter(np.array([len(data.extra)]), PARAMETER_INT, "trailing points that are not markers"),
    }
    codes = flags.T[flags.T >= FLAG_ESTIMATED]
    runs = _encode_runs(codes) if codes.size else np.zeros((2, 0))
    if runs.shape[1] > RUNS_PER_PARAMETER * MAX_RUN_PARAMETERS:
        warnings.warn(f"{path}: {runs.shape[1]} runs of estimation codes do not fit in a C3D parameter section; "
                      "estimated samples will read back as FLAG_ESTIMATED", stacklevel=2)
        runs = np.zeros((2, 0))
    for index, start in enumerate(range(0, runs.shape[1], RUNS_PER_PARAMETER)):
        name = "FLAG_RUNS" + (str(index + 1) if index else "")
        group[name] = _parameter(runs[:, start : start + RUNS_PER_PARAMETER], PARAMETER_FLOAT,
                                 "estimation code and sample count of each run of computed samples")
    c3d["parameters"][GROUP] = group

    # ezc3d appends ".c3d" to any other name: write next to the target, then move it into place.
    partial = path.with_name(f".{path.name}.partial.c3d")
    try:
        c3d.write(str(partial), first_frame_as_zero=first == 0)
        os.replace(partial, path)
    except Exception as exc:
        partial.unlink(missing_ok=True)
        raise MocapFileError(f"{path}: cannot write C3D file ({_one_line(exc)})") from exc


def _words(number: int) -> np.ndarray:
    """A frame number as the two 16-bit words of TRIAL:*_FIELD, each as the signed value a C3D INT holds."""
    words = np.array([number & 0xFFFF, number >> 16 & 0xFFFF])
    return np.where(words > 0x7FFF, words - 0x10000, words)
