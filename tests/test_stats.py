"""A node's latency figures: over the latest frames while it runs, over its whole run once it has ended."""

from __future__ import annotations

import time

import numpy as np

from mocapflow.runtime.runner import RECENT, LatencyHistogram, Stats


def test_latency_covers_the_latest_frames_while_a_node_runs_and_its_whole_run_once_ended() -> None:
    stats = Stats()
    for i in range(RECENT + 200):  # the first 200 frames a second late, the others a millisecond
        stats.frame_done(time.time_ns() - (1_000_000_000 if i < 200 else 1_000_000))
    live, ended = stats.snapshot("n", "running"), stats.snapshot("n", "finished")
    assert live.latency_p99_ms is not None and 1.0 <= live.latency_p99_ms < 2.0
    assert ended.latency_p99_ms is not None and 990 < ended.latency_p99_ms < 1011
    assert ended.latency_p50_ms is not None and 0.99 < ended.latency_p50_ms < 1.5


def test_the_whole_run_latency_percentiles_are_right_to_one_percent_either_side_of_zero() -> None:
    histogram = LatencyHistogram()
    assert histogram.percentiles([50]) is None
    rng = np.random.default_rng(5)
    values = rng.lognormal(0.0, 2.0, 5000) * rng.choice([-1.0, 1.0], 5000, p=[0.1, 0.9])  # skewed clocks: some < 0
    for value in values:
        histogram.add(float(value))
    qs = [1.0, 5.0, 10.0, 50.0, 90.0, 99.0, 99.9]
    got = histogram.percentiles(qs)
    assert got is not None
    # to within 1 %, or a microsecond (under which a latency counts as 0)
    assert np.allclose(got, np.percentile(values, qs, method="inverted_cdf"), rtol=0.01, atol=1e-3)
    tiny = LatencyHistogram()
    for value in (1e-5, -1e-5, float("nan")):
        tiny.add(value)
    assert tiny.percentiles([50]) == [0.0]
