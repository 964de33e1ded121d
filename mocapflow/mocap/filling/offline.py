"""The filler over a whole recording: frame by frame, exactly as a live stream would be filled (the commands, the
tests and the benchmarks all drive it through here), or, for a file, both ways (``fill_both_ways``)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from mocapflow.mocap.filling.config import FillerConfig
from mocapflow.mocap.filling.filter import GapFiller
from mocapflow.mocap.filling.posture import gaps, posture_fill
from mocapflow.mocap.flags import FillCase
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


def fill_both_ways(
    positions: np.ndarray, labels: list[str], rate: float, config: FillerConfig | None = None,
    skeleton: SkeletonModel | None = None, *, rays: np.ndarray | None = None, joints: Sequence[str] = (),
    progress: Progress | None = None,
) -> FilledRecording:
    """Fill a recording with the frames on both sides of every gap, by two estimates weighed by how well each did on
    this very recording.

    - The rigid-body filler both ways (``_both_passes``): the same causal filler run forwards and backwards in time,
      blended across each gap from the forward estimate at its start to the backward one at its end.
    - The whole body's postures (``posture.posture_fill``), which meet the marker's trajectory at both ends of its gap.

    Each marker's samples are their mean weighted by the inverse of each estimate's mean squared error on trial gaps:
    for every gap of the marker, a stretch of the same length where it is seen, nearest the gap, hidden and filled both
    ways (``trial_gaps``). A marker with no such stretch takes the rigid-body filler's estimate, except where no body
    constraint placed it (flag ``KALMAN``: its filter coasting from each side, a straight line), which the postures
    replace. A sample's flag is that of the estimate that weighs more (``POSTURE`` for the postures). Where a frame
    shows no marker at all, the filler's estimate stays. Every marker seen once is filled in every frame. Files only:
    a live stream has no frames after a gap.
    """
    positions = np.asarray(positions, dtype=float)
    config = (config or FillerConfig()).model_copy(update={"extrapolate_max_s": None})
    filled = _both_passes(positions, labels, rate, config, skeleton, rays, joints, progress)
    hidden = ~np.isfinite(positions).all(axis=-1)
    if not hidden.any():
        return filled
    postures = posture_fill(positions)
    trial = trial_gaps(hidden)
    weight = np.where(filled.flags == FillCase.KALMAN, 1.0, 0.0)  # of the postures: no constraint, no trial
    if trial.any():
        tried = np.where(trial[..., None], np.nan, positions)
        errors = [np.where(trial, ((estimate - positions) ** 2).sum(-1), 0.0).sum(0) / np.maximum(trial.sum(0), 1)
                  for estimate in (_both_passes(tried, labels, rate, config, skeleton, rays, (), None).positions,
                                   posture_fill(tried))]
        known = trial.any(0) & np.isfinite(errors[0]) & np.isfinite(errors[1])
        share = errors[0] / np.maximum(errors[0] + errors[1], 1e-12)  # 1/e_p^2 / (1/e_f^2 + 1/e_p^2)
        weight = np.where(known[None] & (filled.flags != FillCase.KALMAN), share[None], weight)
    weight = np.where(hidden & np.isfinite(postures).all(-1), weight, 0.0)
    w = weight[..., None]
    out = filled.positions * (1 - w) + np.where(w > 0, postures, 0.0) * w
    flags = np.where(weight > 0.5, FillCase.POSTURE, filled.flags).astype(filled.flags.dtype)
    return FilledRecording(out, flags, filled.joint_centres)


def _both_passes(positions: np.ndarray, labels: list[str], rate: float, config: FillerConfig,
                 skeleton: SkeletonModel | None, rays: np.ndarray | None, joints: Sequence[str],
                 progress: Progress | None) -> FilledRecording:
    """The causal filler forwards and backwards, blended across each gap (the forward pass alone for a gap at the end
    of the recording, the backward one for a gap at its start). A sample's flag is that of the pass with the larger
    weight."""
    reverse = None if rays is None else rays[::-1]
    ahead = fill_recording(positions, labels, rate, config, skeleton, rays=rays, joints=joints, progress=progress)
    behind = fill_recording(positions[::-1], labels, rate, config, skeleton, rays=reverse, joints=joints,
                            progress=progress)
    back = backward_weights(~np.isfinite(positions).all(axis=-1))
    back = np.where(np.isfinite(behind.positions[::-1]).all(-1), back, 0.0)
    back = np.where(np.isfinite(ahead.positions).all(-1), back, 1.0)[..., None]
    out = np.where(back > 0, behind.positions[::-1], 0.0) * back + np.where(back < 1, ahead.positions, 0.0) * (1 - back)
    flags = np.where(back[..., 0] > 0.5, behind.flags[::-1], ahead.flags)
    centres = {name: either_or_mean(ahead.joint_centres[name], behind.joint_centres[name][::-1])
               for name in ahead.joint_centres}
    return FilledRecording(out, flags, centres)


def trial_gaps(hidden: np.ndarray) -> np.ndarray:
    """(F, N) for every gap of every marker in ``hidden`` (F, N), a stretch of the same length where the marker is
    seen, with a seen frame on either side, nearest the gap and apart from its other gaps and trial stretches; none
    for a gap no such stretch fits."""
    frames, n = hidden.shape
    trial = np.zeros_like(hidden)
    for m in range(n):
        taken = hidden[:, m].copy()
        for start, stop in gaps(taken):
            length = stop - start
            # c is free when frames c - 1 .. c + length are neither hidden nor taken
            busy = np.concatenate([[0], np.cumsum(taken)])
            first = np.arange(1, frames - length)
            free = first[busy[first + length + 1] - busy[first - 1] == 0]
            if len(free):
                c = free[np.argmin(np.abs(free - start))]
                trial[c:c + length, m] = True
                taken[c - 1:c + length + 1] = True
    return trial


def either_or_mean(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(F, 3) the mean of two tracks where both are known, the known one where one is, NaN where neither is."""
    known_a, known_b = np.isfinite(a).all(-1, keepdims=True), np.isfinite(b).all(-1, keepdims=True)
    total = np.where(known_a, a, 0.0) + np.where(known_b, b, 0.0)
    count = known_a.astype(int) + known_b
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def backward_weights(missing: np.ndarray) -> np.ndarray:
    """(F, N) the backward pass's weight per sample: 0 where observed, rising linearly across each gap of a marker
    from just above 0 after its last sighting to just below 1 before its next; 1 throughout a gap at the start, 0
    throughout one at the end (and 1/2 for a marker never seen)."""
    frames, n = missing.shape
    weight = np.zeros((frames, n))
    for m in range(n):
        for start, stop in gaps(missing[:, m]):
            if start == 0 and stop == frames:
                weight[:, m] = 0.5
            elif start == 0:
                weight[:stop, m] = 1.0
            elif stop < frames:
                weight[start:stop, m] = np.arange(1, stop - start + 1) / (stop - start + 1)
    return weight
