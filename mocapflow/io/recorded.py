"""A recorder's frame log (``mocapflow.io.framelog``) made into a C3D or TRC file, in two passes of bounded memory.

The first pass learns the frame numbers, the widest marker set and its labels, the joint names and the rate; the
second fills one array of the output's size. The first copy of each frame number is kept (a later one never replaces
a real frame). Frame numbers far from the bulk of the recording (an isolated frame 10**12) and frames of far more
markers than the others would make the output absurdly large: they are left out and counted in the log.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from mocapflow.io.framelog import scan
from mocapflow.io.markers import MarkerData, write_markers
from mocapflow.messages import MarkerFrame, Pose, decode

PORTS = {"markers": 0, "pose": 1}
GAP = 100_000
"""Frames further than this from every other recorded frame belong to no plausible span of the recording."""
WIDTH_FACTOR = 4
"""Frames of more markers than this many times the median are left out."""


def _main_span(frames: np.ndarray) -> tuple[int, int]:
    """First and last frame of the largest group of frame numbers with no gap over ``GAP``."""
    frames = np.unique(frames)
    cuts = np.flatnonzero(np.diff(frames) > GAP) + 1
    groups = np.split(frames, cuts)
    best = max(groups, key=len)
    return int(best[0]), int(best[-1])


def convert_log(log_path: Path, out: Path, log: logging.Logger) -> bool:
    """Write ``out`` from the log at ``log_path``; False (and a warning) when it holds no frame."""
    numbers, widths, rate, labels = [], [], 0.0, None
    joints: dict[str, int] = {}
    for port, payload in scan(log_path)[2]:
        if port == PORTS["markers"]:
            m = decode(payload, MarkerFrame)
            numbers.append(m.frame)
            widths.append(len(m.positions))
            rate = m.rate
            if m.labels is not None and (labels is None or len(m.labels) >= len(labels)):
                labels = m.labels
        else:
            for name in decode(payload, Pose).joint_names:
                joints.setdefault(name, len(joints))
    if not numbers:
        log.warning("no frame received: %s not written", out)
        return False
    limit = WIDTH_FACTOR * max(int(np.median(widths)), 1)
    first, last = _main_span(np.array([n for n, w in zip(numbers, widths, strict=True) if w <= limit]))
    width = max(w for n, w in zip(numbers, widths, strict=True) if first <= n <= last and w <= limit)
    count = last - first + 1
    positions = np.full((count, width, 3), np.nan)
    flags = np.zeros((count, width), np.uint8)
    has_flags = False
    extra = np.full((len(joints), count, 3), np.nan)
    seen = np.zeros(count, bool)
    posed = np.zeros(count, bool)
    left_out = duplicates = 0
    for port, payload in scan(log_path)[2]:
        m = decode(payload, MarkerFrame if port == PORTS["markers"] else Pose)
        i = m.frame - first
        if not 0 <= i < count:
            left_out += 1
            continue
        if isinstance(m, Pose):
            if not posed[i]:
                posed[i] = True
                centres = np.asarray(m.joint_centres, dtype=float)
                for j, name in enumerate(m.joint_names):
                    extra[joints[name], i] = centres[j]
            continue
        if seen[i]:
            duplicates += 1
            continue
        if len(m.positions) > width:
            left_out += 1
            continue
        seen[i] = True
        positions[i, : len(m.positions)] = m.positions
        if m.flags is not None:
            flags[i, : len(m.flags)] = m.flags
            has_flags = True
    if left_out or duplicates:
        log.warning("%s: %d implausible frames left out (numbers far from frames %d..%d, or over %d markers); "
                    "%d repeated frame numbers, the first copy kept", out, left_out, first, last, limit, duplicates)
    names = labels if labels and len(labels) == width else [f"P{i + 1:03d}" for i in range(width)]
    out.parent.mkdir(parents=True, exist_ok=True)
    write_markers(out, MarkerData(positions=positions, labels=names, rate=rate, first_frame=first,
                                  flags=flags if has_flags else None,
                                  extra={name: extra[j] for name, j in joints.items()}))
    log.info("wrote %d frames x %d markers to %s", count, width, out)
    return True
