"""Inbox policies: ``queue: all`` keeps every message up to a bound and counts what it refuses, ``queue: latest`` keeps
the newest and counts what it passes over, ``queue: preview`` takes the newest of a thinned copy, ``queue: sampled``
every frame of a sampled copy; the backlog is reported. Unit tests of the inbox and of sampling, then real runs."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import CLI

from mocapflow.errors import GraphError
from mocapflow.messages import MarkerFrame
from mocapflow.runtime.graph import load_graph
from mocapflow.runtime.inbox import Inbox
from mocapflow.runtime.preview import PREVIEW_HZ
from mocapflow.runtime.runner import Runner
from mocapflow.runtime.sampling import SAMPLED_HZ, Sampler, base_stride

TESTS = Path(__file__).resolve().parent


def test_latest_keeps_the_newest_and_counts_the_rest() -> None:
    inbox: Inbox[int] = Inbox(latest={"view"})
    for i in range(5):
        inbox.put("view", i)
    inbox.put("data", 100)
    inbox.put("view", 5)
    assert inbox.backlog()[0] == 2
    first, second = inbox.get(0), inbox.get(0)
    assert first is not None and (first.port, first.item, first.skipped) == ("view", 5, 5)
    assert second is not None and (second.port, second.item, second.skipped) == ("data", 100, 0)
    assert inbox.get(0) is None and inbox.skipped == {"view": 5} and inbox.drops == {}
    inbox.put("view", 6)
    inbox.put("view", 0, end=True)  # end of stream is never replaced
    inbox.put("view", 7)
    got = [inbox.get(0) for _ in range(3)]  # 7 replaced 6 where it waited, ahead of the end
    assert [(e.item, e.end, e.skipped) for e in got if e is not None] == [(7, False, 1), (0, True, 0)]


def test_all_is_bounded_counts_what_it_refuses_and_never_refuses_an_end() -> None:
    inbox: Inbox[int] = Inbox(capacity=3)
    assert [inbox.put("m", i) for i in range(5)] == [True, True, True, False, False]
    assert inbox.put("m", -1, end=True)
    assert inbox.drops == {"m": 2} and inbox.backlog()[0] == 4
    got = [inbox.get(0) for _ in range(4)]
    assert [e.item for e in got if e is not None] == [0, 1, 2, -1]
    assert got[3] is not None and got[3].end and got[3].skipped == 2  # the gap before the end is accounted for
    figures = inbox.figures({"m"})
    assert (figures["drops"], figures["skipped"], figures["backlog"], figures["backlog_max"]) == (2, 0, 0, 4)


@pytest.mark.parametrize("rate", [50.0, 100.0, 120.0, 240.0, 500.0, 1000.0, 2000.0])
@pytest.mark.parametrize("hz", [30.0, 60.0, 100.0, 500.0])
def test_a_stage_takes_the_same_samples_from_the_whole_stream_and_from_its_sampled_copy(rate: float,
                                                                                       hz: float) -> None:
    frames = np.arange(3 * int(rate))
    copy = frames[frames % base_stride(rate) == 0]
    sampler = Sampler(hz)
    whole = [f for f in frames if sampler.take(int(f), rate)]
    assert whole == [f for f in copy if sampler.take(int(f), rate)]
    # about the rate asked for, never more than the copy carries (every frame of a slower stream)
    taken = len(whole) / 3
    assert taken <= max(SAMPLED_HZ, rate / base_stride(rate)) + 1 and abs(sampler.rate(rate) - taken) <= 1 / 3
    assert taken == rate or abs(taken - min(hz, rate / base_stride(rate))) <= 0.5 * min(hz, rate) + 1


def test_a_sampled_copy_counts_the_frames_it_leaves_out_as_skipped_and_a_missing_sample_as_lost(
        tmp_path: Path) -> None:
    from slow_sink import SlowSink

    runner = Runner("sink", SlowSink, SlowSink.Config(path=str(tmp_path / "h.txt"), delay_s=0), lambda *a: None,
                    {"markers"})
    for frame in (0, 8, 16, 32):  # the copy of a 960 Hz stream carries every 8th frame; 24 was lost
        message = MarkerFrame(frame=frame, capture_ns=1, rate=960.0, positions=np.zeros((1, 3)))
        runner.count_in("markers", message, runner.thinned("markers", frame, 0, base_stride(960.0)))
    assert (runner.stats.frames_in, runner.stats.drops, runner.stats.passed) == (4, 1, 28)


def test_a_queue_policy_must_name_a_linked_input(tmp_path: Path) -> None:
    path = tmp_path / "g.yaml"
    path.write_text("name: q\nnodes:\n  tracker: {plugin: simulator}\n"
                    "  relay: {plugin: relay, inputs: {markers: tracker/markers}, queue: {marker: latest}}\n")
    with pytest.raises(GraphError, match="nodes.relay.queue.marker: no linked input 'marker'"):
        load_graph(path)
    path.write_text("name: q\nnodes:\n  tracker: {plugin: simulator}\n"
                    "  relay: {plugin: relay, inputs: {markers: tracker/markers}, queue: {markers: newest}}\n")
    with pytest.raises(GraphError, match="nodes.relay.queue.markers"):
        load_graph(path)


def _run_slow_sink(tmp_path: Path, endpoint: str, frames: int, policy: str, group: str = "",
                   config: str = "delay_s: 0.02", rate: int = 200) -> tuple[list[int], dict]:
    out = tmp_path / "handled.txt"
    summary = tmp_path / "summary.json"
    path = tmp_path / "g.yaml"
    path.write_text(
        f"name: queue\nzenoh: {{listen: ['{endpoint}']}}\nnodes:\n"
        f"  tracker: {{plugin: simulator, {group} config: {{rig: rods, rate: {rate}, frames: {frames}}}}}\n"
        f"  sink: {{plugin: 'slow_sink:SlowSink', inputs: {{markers: tracker/markers}}, {policy}, {group}\n"
        f"          config: {{path: '{out}', {config}}}}}\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(TESTS), os.environ.get("PYTHONPATH")]))}
    run = subprocess.run([*CLI, "run", str(path), "--summary", str(summary)], capture_output=True, text=True,
                         timeout=90, env=env, check=False)
    assert run.returncode == 0, run.stdout + run.stderr
    handled = [int(line) for line in out.read_text().split()]
    return handled, json.loads(summary.read_text())["sink"]


@pytest.mark.integration
def test_latest_drops_only_what_it_says(tmp_path: Path, free_endpoint: str) -> None:
    """A sink four times too slow for its source: it handles the newest frames in order, and every frame it did
    not handle is counted as skipped, none lost unaccounted."""
    frames = 200
    handled, stats = _run_slow_sink(tmp_path, free_endpoint, frames, "queue: {markers: latest}")
    assert handled == sorted(set(handled)) and handled[-1] == frames - 1
    assert 0 < stats["skipped"] and len(handled) + stats["skipped"] == frames, (len(handled), stats)
    assert stats["drops"] == 0 and stats["frames_in"] == len(handled)
    assert stats["backlog_max"] <= 2  # never more than the newest frame (and the end of stream) waiting


@pytest.mark.integration
def test_a_node_process_keeps_what_its_setup_made_out_of_the_collectors_full_passes(tmp_path: Path,
                                                                                     free_endpoint: str) -> None:
    """The interpreter's, the libraries' and the nodes' objects are frozen before the stream starts: a full pass of
    the garbage collector, which would stop the frame loop for tens of milliseconds, sees only what the stream made."""
    _run_slow_sink(tmp_path, free_endpoint, 100, "queue: {markers: all}", config="delay_s: 0")
    frozen, tracked = (int(n) for n in (tmp_path / "handled.txt.gc").read_text().split())
    assert frozen > 10_000, frozen  # numpy, pydantic, zenoh and the node: tens of thousands of objects
    assert tracked < frozen / 10, (frozen, tracked)


@pytest.mark.integration
def test_a_full_inbox_drops_and_counts(tmp_path: Path, free_endpoint: str) -> None:
    frames = 200
    handled, stats = _run_slow_sink(tmp_path, free_endpoint, frames, "queue_size: 10")
    assert handled == sorted(set(handled)) and handled[:10] == list(range(10))
    assert stats["drops"] > 0 and len(handled) + stats["drops"] == frames, (len(handled), stats)
    assert stats["skipped"] == 0 and 10 <= stats["backlog_max"] <= 11 and stats["backlog_max_ms"] > 100


@pytest.mark.integration
@pytest.mark.parametrize("group", ["", "group: one,"], ids=["over Zenoh", "in a group"])
def test_a_node_is_handed_only_the_messages_it_wants(tmp_path: Path, free_endpoint: str, group: str) -> None:
    """A node that samples its input (every fourth frame) is handed just those, in order, whether they come over
    Zenoh (the others are not even decoded) or inside its group; the others are counted as skipped, none as lost."""
    frames = 200
    handled, stats = _run_slow_sink(tmp_path, free_endpoint, frames, "queue: {markers: all}", group,
                                    "delay_s: 0, every: 4")
    assert handled == list(range(0, frames, 4))
    assert stats["frames_in"] == len(handled) and stats["skipped"] == frames - len(handled), stats
    assert stats["drops"] == 0 and stats["errors"] == 0


@pytest.mark.integration
@pytest.mark.parametrize("group", ["", "group: one,"], ids=["over Zenoh", "in a group"])
def test_a_latest_input_hands_over_its_last_frame_passed_over(tmp_path: Path, free_endpoint: str,
                                                                group: str) -> None:
    """A sink that samples a 'latest' input (as a viewer does at its display rate) is still handed the stream's last
    frame, passed over when it came, before the stream ends; it is counted in, not as skipped."""
    frames = 200  # the last, 199, is not one of every seventh
    handled, stats = _run_slow_sink(tmp_path, free_endpoint, frames, "queue: {markers: latest}", group,
                                    "delay_s: 0, every: 7")
    assert handled == sorted(set(handled)) and handled[-1] == frames - 1 and len(handled) < frames, handled
    if group:  # inside the group every frame is offered in turn
        assert handled == [*range(0, frames, 7), frames - 1]
    assert stats["frames_in"] == len(handled) and stats["skipped"] == frames - len(handled), stats
    assert stats["drops"] == 0 and stats["errors"] == 0


@pytest.mark.integration
def test_a_preview_input_takes_at_most_a_display_rate_with_the_last_frame(tmp_path: Path,
                                                                           free_endpoint: str) -> None:
    """An input on an output's preview ('queue: preview') receives at most 60 of the 200 frames a second, in order,
    the last one included; the frames the preview left out are counted as skipped, none as lost."""
    frames = 400  # two seconds
    handled, stats = _run_slow_sink(tmp_path, free_endpoint, frames, "queue: {markers: preview}", "", "delay_s: 0")
    assert handled == sorted(set(handled)) and handled[-1] == frames - 1, handled
    # the tracker stamps each frame as it sends it: over the span of the preview's frames (the last one, sent at the
    # end, aside), at most 60 a second, however fast or slow the machine ran (a late send shifts an end of the span
    # by a frame at most)
    captured = np.array([int(t) for t in (tmp_path / "handled.txt.capture").read_text().split()])
    span_s = (captured[-2] - captured[0]) / 1e9
    assert len(handled) < frames and len(handled) - 2 <= span_s * PREVIEW_HZ + 2, (len(handled), span_s)
    assert stats["frames_in"] == len(handled) and stats["skipped"] == frames - len(handled), stats
    assert stats["drops"] == 0 and stats["errors"] == 0


@pytest.mark.integration
def test_a_sampled_input_takes_every_frame_of_the_sampled_copy(tmp_path: Path, free_endpoint: str) -> None:
    """An input on an output's sampled copy ('queue: sampled', a model stage's) receives, in order, exactly the frames
    whose number is a multiple of the copy's stride (every fourth of a 480 Hz stream), and the end; the frames the
    copy left out are counted as skipped, none as lost."""
    frames = 480
    handled, stats = _run_slow_sink(tmp_path, free_endpoint, frames, "queue: {markers: sampled}", "", "delay_s: 0",
                                    rate=480)
    assert handled == list(range(0, frames, base_stride(480.0))) and base_stride(480.0) == 4, handled
    assert stats["frames_in"] == len(handled) and stats["skipped"] == frames - len(handled) - 3, stats
    assert stats["drops"] == 0 and stats["errors"] == 0
