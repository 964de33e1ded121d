"""The filler over a whole recording: frame by frame, exactly as a live stream would be filled (the commands, the
tests and the benchmarks all drive it through here)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from mocapflow.mocap.filling.config import FillerConfig
from mocapflow.mocap.filling.filter import GapFiller
from mocapflow.mocap.model import SkeletonModel
from mocapflow.mocap.report import Progress, steps


class FilledRecording(NamedTuple):
    """``positions`` (F, N, 3) and ``flags`` (F, N) of the filled recording; ``joint_centres``: per joint asked for,
    its centre in every frame (F, 3), NaN where unknown."""

    positions: np.ndarray
    flags: np.ndarray
    joint_centres: dict[str, np.ndarray]


def fill_recording(
    positions: np.ndarray, labels: list[str], rate: float, config: FillerConfig | None = None,
    skeleton: SkeletonModel | None = None, *, rays: np.ndarray | None = None, joints: Sequence[str] = (),
    progress: Progress | None = None,
) -> FilledRecording:
    """Fill a recording (F, N, 3), with the single-camera ``rays`` (F, N, 6) of its frames when given, and track the
    centres of the named ``joints`` through it."""
    positions = np.asarray(positions, dtype=float)
    filler = GapFiller(labels, rate, config, skeleton)
    out = np.full(positions.shape, np.nan)
    flags = np.zeros(positions.shape[:2], dtype=np.uint8)
    centres = {name: np.full((len(positions), 3), np.nan) for name in joints}
    for f in steps(range(len(positions)), len(positions), "fill", progress):
        result = filler.update(positions[f], None if rays is None else rays[f])
        out[f], flags[f] = result.positions, result.flags
        if centres and result.joint_centres is not None:  # by name: learned joint offsets change the body
            for name, centre in zip(filler.joint_names, result.joint_centres, strict=True):
                if name in centres:
                    centres[name][f] = centre
    return FilledRecording(out, flags, centres)


def fill_sequence(
    positions: np.ndarray, labels: list[str], rate: float, config: FillerConfig | None = None,
    skeleton: SkeletonModel | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``fill_recording``'s positions and flags."""
    filled = fill_recording(positions, labels, rate, config, skeleton)
    return filled.positions, filled.flags
