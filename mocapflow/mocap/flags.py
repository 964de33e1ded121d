"""The per-sample flag: how a marker position in a frame was obtained. Every stage and file format uses these
codes (``MarkerFrame.flags``, C3D residual words, the occlusion filler's cases)."""

from __future__ import annotations

from enum import IntEnum


class FillCase(IntEnum):
    """Per-sample flag: missing, observed, or estimated (2 and up) and by which of the occlusion filler's cases
    (Aristidou 2008, 5.3)."""

    MISSING = 0  # unfillable, left NaN
    OBSERVED = 1
    KALMAN = 2  # the marker's own filter only; the lowest estimated code
    ONE_MISSING = 3  # two or more markers of the segment visible (rigid fit, or the two-sphere circle)
    TWO_MISSING = 4  # one marker of the segment visible (rotated offset)
    VIA_JOINT = 5  # whole segment hidden, placed through the neighbour's centre of rotation
    CONSTANT_ROTOR = 6  # segment and neighbours hidden: through an estimated neighbour's joint, else constant rotor
    RAY = 7  # seen by a single camera: on its ray
    LEARNT = 8  # whole segment hidden, placed by the kinematic model learnt from its visible neighbours
    POSTURE = 9  # offline only: from the whole body's postures fitted to the visible markers (filling.posture)


SampleFlag = FillCase
"""The same enum under the name the file formats use."""

# The codes as plain ints, for per-frame array comparisons: numpy compares an IntEnum member several times slower
CASE_MISSING, CASE_OBSERVED, CASE_KALMAN = int(FillCase.MISSING), int(FillCase.OBSERVED), int(FillCase.KALMAN)
CASE_ONE_MISSING, CASE_TWO_MISSING = int(FillCase.ONE_MISSING), int(FillCase.TWO_MISSING)
