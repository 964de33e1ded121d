"""Frame numbering and clock mapping shared by the live tracker adapters (``mocapflow.trackers.live``)."""

from __future__ import annotations

import numpy as np

from mocapflow.trackers.live import FrameNumbers, LabelRows, TrackerClock

S = 1_000_000_000


def test_clock_offset_is_the_least_delayed_packets() -> None:
    rng = np.random.default_rng(3)
    clock = TrackerClock(window_s=5)
    rate, skew = 120.0, 7 * S  # the tracker's clock is 7 s behind this machine's
    stamps = []
    for i in range(2400):
        tracker_ns = round(i / rate * S)
        delay = 300_000 + int(rng.exponential(2_000_000))  # 0.3 ms minimum, milliseconds of jitter
        stamps.append(clock.stamp(tracker_ns, tracker_ns + skew + delay) - tracker_ns - skew)
    settled = np.array(stamps[240:])
    assert settled.min() >= 300_000  # never before the frame could have been captured plus the fastest transit
    assert settled.max() - settled.min() < 100_000  # the offset holds within 0.1 ms while arrivals scatter by ms


def test_clock_follows_drift_through_its_window() -> None:
    clock = TrackerClock(window_s=1)
    drift = 1e-4  # this machine's clock runs 100 ppm fast
    errors = []
    for i in range(120 * 30):
        tracker_ns = round(i / 120 * S)
        arrival = round(tracker_ns * (1 + drift)) + 500_000
        errors.append(clock.stamp(tracker_ns, arrival) - (arrival - 500_000))  # minus the true capture time
    # late by the drift over one window (0.1 ms), not over the whole run (3 ms); early by the 0.5 ms transit it
    # cannot tell from the offset
    assert 0.5e6 - 0.11e6 < errors[-1] <= 0.5e6 - 0.09e6


def test_clock_reset_forgets_the_old_offset() -> None:
    clock = TrackerClock()
    clock.stamp(0, 10 * S)
    clock.reset()
    assert clock.stamp(0, 50 * S) == 50 * S


def test_frame_numbers_continue_after_a_restarted_count() -> None:
    numbers = FrameNumbers()
    ms = 1_000_000
    assert [numbers.number(f, f * 8 * ms, 120) for f in (100, 101, 103)] == [100, 101, 103]  # a gap stays a gap
    assert numbers.number(103, 103 * 8 * ms + ms, 120) is None  # a duplicate
    assert numbers.number(90, 103 * 8 * ms + 2 * ms, 120) is None  # a stale packet
    resumed = numbers.number(1, 103 * 8 * ms + 2 * S, 120)  # the tracker restarted two seconds later
    assert resumed == 103 + 240
    assert numbers.number(2, 103 * 8 * ms + 2 * S + 8 * ms, 120) == resumed + 1


def test_frame_numbers_keep_a_tracker_that_kept_counting() -> None:
    numbers = FrameNumbers()
    numbers.number(500, 0, 100)
    assert numbers.number(800, 3 * S, 100) == 800  # the network dropped three seconds: 299 frames of drops


def test_label_rows_are_fixed_and_new_labels_appended() -> None:
    rows = LabelRows()
    assert rows.rows(["a", "b"]).tolist() == [0, 1]
    assert rows.rows(["c", "a"]).tolist() == [2, 0]
    assert rows.labels == ["a", "b", "c"]
    assert LabelRows.clean(["Bob:LASI", "Bob:RASI"]) == ["LASI", "RASI"]
