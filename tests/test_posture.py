"""The whole body's postures in the offline fill: a marker no body constraint places is read from the principal
postures of the recording, shifted to meet its trajectory at both ends of its gap."""

from __future__ import annotations

import numpy as np

from mocapflow.mocap.filling import FillCase, FillerConfig, fill_both_ways
from mocapflow.mocap.filling.posture import interpolate_linear, posture_fill
from mocapflow.mocap.simulator import SimulatorConfig, simulate

RATE = 60.0


def test_postures_fill_what_no_constraint_places_better_than_a_straight_line() -> None:
    rec = simulate(SimulatorConfig(rig="human", rate=RATE, noise_mm=0.5, skin_mm=1.0, seed=3), 480)
    x = rec.positions.copy()
    hand = [rec.labels.index(m) for m in ("LFA2", "RFA1")]
    gap = slice(200, 260)  # one second, mid-swing
    x[gap, hand] = np.nan
    x[:30, rec.labels.index("LTH1")] = np.nan  # a gap at the start: one side only

    # no skeleton and nothing learnt: no marker belongs to a segment, so both passes place them by their filters alone
    both = fill_both_ways(x, rec.labels, rec.rate, FillerConfig(learn=False))
    hidden = ~np.isfinite(x).all(-1)
    assert (both.flags[hidden] == FillCase.POSTURE).all()
    observed = ~hidden
    np.testing.assert_array_equal(both.positions[observed], x[observed])

    def error(filled: np.ndarray) -> float:
        return float(np.linalg.norm(filled[gap, hand] - rec.true_positions[gap, hand], axis=-1).mean())

    line = interpolate_linear(x)
    assert error(both.positions) < 0.5 * error(line), (error(both.positions), error(line))
    # the reconstruction meets the observed trajectory at both ends of the gap: no jump in or out of it
    for m in hand:
        for inside, outside in ((gap.start, gap.start - 1), (gap.stop - 1, gap.stop)):
            step = np.linalg.norm(both.positions[inside, m] - x[outside, m])
            assert step < 3 * np.linalg.norm(np.diff(rec.true_positions[gap, m], axis=0), axis=-1).max(), step
    paper = posture_fill(x, meet_ends=False)
    assert error(both.positions) < error(paper)  # meeting the ends improves on the paper's reconstruction


def test_postures_leave_a_frame_with_no_marker_and_a_complete_recording_alone() -> None:
    rec = simulate(SimulatorConfig(rig="human", rate=RATE, seed=4), 120)
    x = rec.positions.copy()
    np.testing.assert_array_equal(posture_fill(x), x)
    x[50] = np.nan
    x[60:70, 3] = np.nan
    filled = posture_fill(x)
    assert np.isnan(filled[50]).all() and np.isfinite(filled[60:70, 3]).all()
