"""Wild samples in a recorded trajectory: a reflection or a glitch that takes a marker metres away for a few frames.

A sample further than ``distance_mm`` from the median of its marker's samples over ``window`` frames around it is
treated as missing. A spike shorter than half the window cannot move that median, and no marker strays a metre from
where it was a fraction of a second around, so real motion is kept.
"""

from __future__ import annotations

import warnings

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

CHUNK = 4096


def wild_samples(positions: np.ndarray, window: int = 31, distance_mm: float = 1000.0) -> np.ndarray:
    """(F, N) mask of the samples of ``positions`` (F, N, 3) far from the median around them."""
    frames = len(positions)
    half = window // 2
    padded = np.pad(positions, ((half, half), (0, 0), (0, 0)), constant_values=np.nan)
    wild = np.zeros(positions.shape[:2], bool)
    for start in range(0, frames, CHUNK):  # bounded memory: one chunk of windows at a time
        stop = min(start + CHUNK, frames)
        windows = sliding_window_view(padded[start : stop + 2 * half], window, axis=0)  # (n, N, 3, window)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-missing windows
            median = np.nanmedian(windows, axis=-1)
        with np.errstate(invalid="ignore"):
            wild[start:stop] = np.linalg.norm(positions[start:stop] - median, axis=-1) > distance_mm
    return wild
