"""Labelled marker trajectories in memory (``MarkerData``), their sample flags, and the conventions every reader
shares: positions in mm with NaN for a missing sample, whatever the file's units and whatever the exporter wrote for
a gap (NaN, an invalid residual, or exactly 0,0,0), so the algorithms see one convention.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import numpy as np

from mocapflow.errors import MocapFileError
from mocapflow.mocap.flags import SampleFlag

FLAG_MISSING: Final = int(SampleFlag.MISSING)
"""No position for this sample."""
FLAG_OBSERVED: Final = int(SampleFlag.OBSERVED)
"""Position measured by the cameras."""
FLAG_ESTIMATED: Final = int(SampleFlag.KALMAN)
"""Position computed (gap filled) rather than measured; codes 3..FLAG_MAX name which estimation case filled it."""
FLAG_MAX: Final = 15

UNIT_SCALE: Final[dict[str, float]] = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
"""Factor from a file's length unit to mm."""


@dataclass
class MarkerData:
    """Marker trajectories of one recording: what every reader returns and every writer takes.

    ``positions`` is (F, N, 3) in mm with NaN where missing; ``flags`` (F, N) says, per sample, whether it is
    missing, observed or estimated (and how); ``None`` means observed wherever a position exists.
    ``extra`` holds named (F, 3) points that are not markers (joint centres...), written after the markers.
    ``first_frame`` is the file's number of the first frame (C3D numbers frames from 1).
    """

    positions: np.ndarray
    labels: list[str]
    rate: float
    first_frame: int = 0
    flags: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.positions = np.asarray(self.positions, dtype=np.float64)
        self.labels = [str(label) for label in self.labels]
        if self.positions.ndim != 3 or self.positions.shape[2] != 3:
            raise ValueError(f"positions must be (frames, markers, 3), got {self.positions.shape}")
        frames, markers, _ = self.positions.shape
        if len(self.labels) != markers:
            raise ValueError(f"{len(self.labels)} labels for {markers} markers")
        duplicates = [label for label, count in Counter(self.labels).items() if count > 1]
        if duplicates:
            raise ValueError(f"duplicate labels: {duplicates}")
        if not self.rate > 0:
            raise ValueError(f"rate must be positive, got {self.rate}")
        if self.first_frame < 0:
            raise ValueError(f"first_frame must be >= 0, got {self.first_frame}")
        if self.flags is not None:
            self.flags = np.asarray(self.flags)
            if self.flags.shape != (frames, markers):
                raise ValueError(f"flags must be {(frames, markers)}, got {self.flags.shape}")
            if self.flags.size and (self.flags.min() < 0 or self.flags.max() > FLAG_MAX):
                raise ValueError(f"flags must be in 0..{FLAG_MAX}")
            self.flags = self.flags.astype(np.uint8)
        self.extra = {str(name): np.asarray(point, dtype=np.float64) for name, point in self.extra.items()}
        for name, point in self.extra.items():
            if point.shape != (frames, 3):
                raise ValueError(f"extra point {name!r} must be {(frames, 3)}, got {point.shape}")
            if name in self.labels:
                raise ValueError(f"extra point {name!r} has the label of a marker")

    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]

    @property
    def n_markers(self) -> int:
        return self.positions.shape[1]

    def sample_flags(self) -> np.ndarray:
        """Flags of every sample, (F, N) uint8, consistent with the positions, which decide whether a sample exists.

        Stored flags are kept where they agree; a sample with no position is missing, and one with a position but
        no flag (or a missing one) is observed.
        """
        present = np.isfinite(self.positions).all(axis=2)
        stored = np.full(present.shape, FLAG_MISSING, np.uint8) if self.flags is None else self.flags
        return np.where(present, np.maximum(stored, FLAG_OBSERVED), FLAG_MISSING).astype(np.uint8)


def missing_as_nan(positions: np.ndarray) -> np.ndarray:
    """Set to NaN every sample that is not finite or is exactly (0, 0, 0), the gap marker of some exporters."""
    gone = ~np.isfinite(positions).all(axis=-1) | (positions == 0).all(axis=-1)
    positions[gone] = np.nan
    return positions


def unit_scale(units: str, path: Path) -> float:
    """Factor from ``units`` to mm; an empty unit is taken as mm, an unknown one is an error naming the file."""
    key = units.strip().lower() or "mm"
    if key not in UNIT_SCALE:
        raise MocapFileError(f"{path}: unknown length unit {units!r} (expected one of {', '.join(UNIT_SCALE)})")
    return UNIT_SCALE[key]


def clean_labels(raw: Sequence[str], strip_prefix: bool, taken: Sequence[str] = ()) -> list[str]:
    """Unique labels from a file's: blanks named by position, ``Subject:`` prefixes dropped when that is unambiguous.

    A prefix is kept on every label whose stripped name would clash with another one (two subjects with the same
    marker set) or with a name in ``taken``; labels still repeated after that get ``_2``, ``_3``... so each marker
    keeps its own name.
    """
    names = [label.strip() or f"point{index + 1}" for index, label in enumerate(raw)]
    if strip_prefix:
        stripped = [name.rpartition(":")[2] or name for name in names]
        counts = Counter(stripped) + Counter(taken)
        names = [short if counts[short] == 1 else name for name, short in zip(names, stripped, strict=True)]
    used = set(taken)
    unique = []
    for name in names:
        candidate, copy = name, 1
        while candidate in used:
            copy += 1
            candidate = f"{name}_{copy}"
        used.add(candidate)
        unique.append(candidate)
    return unique
