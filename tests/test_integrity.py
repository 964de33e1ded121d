"""What a data input accepts, and the recorder's frame log: the rules one by one, on real files."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli

from mocapflow.io.framelog import FrameLog, scan
from mocapflow.io.markers import read_markers
from mocapflow.io.recorded import PORTS, convert_log
from mocapflow.messages import MarkerFrame, Pose, encode
from mocapflow.runtime.integrity import InputGuard, Refused, StreamLimits

TRACKER, OTHER = b"tracker@1", b"tracker@2"


def frame(number: int, n: int = 3, value: float = 1.0) -> MarkerFrame:
    return MarkerFrame(frame=number, capture_ns=0, rate=100, positions=np.full((n, 3), value))


def accept(guard: InputGuard, identity: bytes | None, message: MarkerFrame, now: float = 0.0) -> MarkerFrame:
    guard.check_source(identity, now)
    return guard.check_frame(message)


def test_frames_and_end_only_from_the_owner() -> None:
    guard = InputGuard(upstream="tracker", limits=StreamLimits())
    assert not guard.accept_end(None) and not guard.accept_end(b"other@1")  # before any frame: only the upstream
    assert guard.accept_end(b"tracker@9")
    accept(guard, TRACKER, frame(0))
    assert not guard.accept_end(OTHER) and not guard.accept_end(None) and guard.accept_end(TRACKER)
    with pytest.raises(Refused, match="while tracker@1 publishes"):
        accept(guard, OTHER, frame(1), now=0.5)
    accept(guard, TRACKER, frame(1), now=0.6)
    # the owner silent for longer than takeover_s: its restart (a new run id) takes over, resuming on its clock
    accept(guard, OTHER, frame(400), now=2.0)
    assert guard.owner == OTHER and guard.accept_end(OTHER) and not guard.accept_end(TRACKER)


def test_frame_numbers_are_plausible_and_a_real_jump_resynchronises() -> None:
    guard = InputGuard(upstream="tracker", limits=StreamLimits(max_frame_jump=100, resync_frames=3))
    for i in range(10):
        accept(guard, TRACKER, frame(i))
    with pytest.raises(Refused, match="frame 10000000 is more than 100 frames after the last accepted frame 9"):
        accept(guard, TRACKER, frame(10_000_000))
    with pytest.raises(Refused, match="frame 5 is not after the last accepted frame 9"):
        accept(guard, TRACKER, frame(5))
    with pytest.raises(Refused, match="not after"):
        accept(guard, TRACKER, frame(9))  # a repeat never replaces the real frame 9
    accept(guard, TRACKER, frame(10))  # the glitches cost nothing
    # a counter that really reset: refused until three consecutive frames agree, then followed
    for i in range(2):
        with pytest.raises(Refused):
            accept(guard, TRACKER, frame(i))
    accept(guard, TRACKER, frame(2))
    accept(guard, TRACKER, frame(3))
    # a restarted publisher may be ahead by what its silence allows at 100 kHz, not by 10**12
    guard.check_source(OTHER, now=12.0)
    with pytest.raises(Refused):
        guard.check_frame(frame(10**12))
    guard.check_frame(frame(3 + 10 * 240))


def test_sizes_and_coordinates_are_bounded() -> None:
    guard = InputGuard(upstream="tracker", limits=StreamLimits(max_markers=10, max_coordinate_mm=1e4))
    with pytest.raises(Refused, match="11 markers"):
        accept(guard, TRACKER, frame(0, n=11))
    with pytest.raises(Refused, match="every coordinate is beyond"):
        accept(guard, TRACKER, frame(0, value=1e30))
    message = frame(0)
    message.positions[1] = [1e30, 0, 0]
    out = accept(guard, TRACKER, message)
    assert np.isnan(out.positions[1]).all() and (out.positions[[0, 2]] == 1).all()
    assert guard.last == 0


def test_the_frame_log_survives_a_cut_and_is_continued_by_the_same_run(tmp_path: Path) -> None:
    path = tmp_path / "out.c3d.part"
    log = FrameLog(path, "run1")
    for i in range(5):
        log.append(PORTS["markers"], encode(frame(i)))
    log.close()
    with path.open("ab") as f:
        f.write(b"\x40\x00\x00\x00\x01\x02")  # a record cut short by a kill
    log = FrameLog(path, "run1")  # the restarted recorder of the same run
    assert log.resumed
    log.append(PORTS["markers"], encode(frame(7)))
    log.close()
    run, _, records = scan(path)
    assert run == "run1" and [p for p, _ in records] == [0] * 6
    other = FrameLog(path, "run2")  # another run never appends to, nor truncates, this one's log
    other.close()
    assert other.set_aside == tmp_path / "out.c3d.part.run1" and len(list(scan(other.set_aside)[2])) == 6
    assert len(list(scan(path)[2])) == 0


def test_conversion_keeps_the_first_copy_and_leaves_out_implausible_frames(tmp_path: Path) -> None:
    path = tmp_path / "out.c3d.part"
    log = FrameLog(path, "r")
    for i in range(20):
        log.append(PORTS["markers"], encode(frame(i, value=i + 1.0)))  # (0, 0, 0) reads back as missing
    log.append(PORTS["markers"], encode(frame(5, value=99.0)))  # a repeated number: must not replace frame 5
    log.append(PORTS["markers"], encode(frame(10**12)))  # would make a 10**12-frame file
    log.append(PORTS["markers"], encode(frame(21, n=5000)))  # would make every frame 5000 markers wide
    log.append(PORTS["pose"], encode(Pose(frame=3, capture_ns=0, joint_names=["hip"], joint_centres=[[1, 2, 3]],
                                          segment_names=[], rotations=np.zeros((0, 4)),
                                          translations=np.zeros((0, 3)))))
    log.close()
    out = tmp_path / "out.c3d"
    assert convert_log(path, out, logging.getLogger("test"))
    data = read_markers(out)
    assert data.positions.shape == (20, 3, 3) and data.first_frame in (0, 1)
    np.testing.assert_allclose(data.positions[:, 0, 0], np.arange(1.0, 21.0))
    np.testing.assert_allclose(data.extra["hip"][3], [1, 2, 3])


@pytest.mark.integration
def test_a_blinded_tracker_does_not_change_identities() -> None:
    """Half a second of frames with no point at all (every camera blinded), then the markers again: the labeller
    node finds them by their layouts instead of opening new tracks."""
    from mocapflow.mocap.labelling import LabellerConfig
    from mocapflow.mocap.simulator import Simulator, SimulatorConfig
    from mocapflow.plugins.labeller import LabellerNode

    rate = 240
    sim = Simulator(SimulatorConfig(rig="human", rate=rate, seed=3, unlabelled=True))
    out: list[MarkerFrame] = []
    node = LabellerNode(LabellerConfig(), lambda _port, message: out.append(message), "labeller")
    identity = {}
    for i in range(6 * rate):
        f = sim.frame(i)
        points = f.points if not 3 * rate <= i < 3 * rate + rate // 2 else np.full((len(f.points), 3), np.nan)
        node.process("markers", MarkerFrame(frame=i, capture_ns=0, rate=rate, positions=points))
        if i in (3 * rate - 1, 6 * rate - 1):  # each label's marker, before the blackout and at the end
            labelled = out[-1].positions
            d = np.linalg.norm(labelled[:, None] - f.points[None], axis=2)  # (labels, points)
            d[np.isnan(d)] = np.inf
            nearest = d.argmin(axis=1)
            identity[i] = {t: int(f.identity[p]) for t, p in enumerate(nearest) if d[t, p] < 1e-3}
    before, after = identity[3 * rate - 1], identity[6 * rate - 1]
    markers = len(sim.rig.marker_labels)
    # no label names another marker; most keep theirs (a segment whose layout fits two ways gets new labels instead)
    assert len(before) >= markers - 5 and len(after) >= markers - 5  # the labelled samples are the real points
    assert all(before[t] == after[t] for t in before.keys() & after.keys()), (before, after)
    kept = sum(before.get(t) == m for t, m in after.items())
    assert kept >= markers // 2 and len(out[-1].labels) <= 2 * markers, (kept, len(out[-1].labels))


@pytest.mark.integration
def test_commands_leave_out_absurd_samples_and_refuse_absurd_files(tmp_path: Path) -> None:
    """A sample no capture volume holds is left out as missing, as live, in one line, and the rest is worked on; a
    file with nothing else, a rate no tracker has or more markers than calibrate takes is refused in one line."""
    from mocapflow.io.markers import MarkerData, write_markers

    positions = np.random.default_rng(0).normal(0, 100, (50, 4, 3))
    positions[10, 2] = [1e6, 0, 0]
    write_markers(tmp_path / "spike.c3d", MarkerData(positions=positions, labels=list("ABCD"), rate=100))
    write_markers(tmp_path / "fast.trc", MarkerData(positions=positions[:, :, :] * 0 + 1, labels=list("ABCD"),
                                                    rate=1e6))
    write_markers(tmp_path / "micrometres.trc", MarkerData(positions=positions * 0 + 2e8, labels=list("ABCD"),
                                                           rate=100))
    write_markers(tmp_path / "wide.c3d", MarkerData(positions=np.zeros((5, 600, 3)),
                                                    labels=[f"M{i}" for i in range(600)], rate=100))

    done = run_cli("calibrate", tmp_path / "wide.c3d", "-o", tmp_path / "out.json")
    assert done.returncode == 2 and len(done.stderr.splitlines()) == 1, done.stderr
    assert "600 markers: calibrate takes at most 500" in done.stderr
    for name, message in (("micrometres.trc", "every sample lies beyond 100 m from the origin (first: A at frame"),
                          ("fast.trc", "a rate of 1e+06 Hz is beyond any tracker")):
        for command, output in (("fill", "out.c3d"), ("calibrate", "out.json"), ("label", "out.c3d")):
            done = run_cli(command, tmp_path / name, "-o", tmp_path / output)
            assert done.returncode == 2 and message in done.stderr and len(done.stderr.splitlines()) == 1, \
                (command, done.stderr)
    done = run_cli("fill", tmp_path / "spike.c3d", "-o", tmp_path / "filled.c3d")
    assert done.returncode == 0, done.stderr
    assert (f"{tmp_path / 'spike.c3d'}: 1 samples beyond 100 m from the origin (first: C at frame 10, "
            "[1000000.0, 0.0, 0.0] mm) left out as missing") in done.stdout.splitlines()
    gap = positions.copy()
    gap[10, 2] = np.nan
    write_markers(tmp_path / "gap.c3d", MarkerData(positions=gap, labels=list("ABCD"), rate=100))
    assert run_cli("fill", tmp_path / "gap.c3d", "-o", tmp_path / "gap_filled.c3d").returncode == 0
    # worked on as if the sample were missing: the same output, bit for bit
    assert np.array_equal(read_markers(tmp_path / "filled.c3d").positions,
                          read_markers(tmp_path / "gap_filled.c3d").positions)


@pytest.mark.parametrize("spike_mm", [1e6, 5000.0])
def test_a_wild_sample_does_not_move_other_markers(spike_mm: float) -> None:
    """One sample far off (a reflection, a glitch) while a segment mate is hidden and filled from it: it is treated
    as missing, so the mate is filled near its true position and every other marker exactly as without it."""
    from mocapflow.mocap.filling import FillerConfig, fill_sequence
    from mocapflow.mocap.simulator import SimulatorConfig, simulate

    rec = simulate(SimulatorConfig(rig="human", rate=120, seed=5, dropout_rate=0.0), 600)
    f, m = 400, 7
    segment = np.array(rec.marker_segment)
    mate = int(np.flatnonzero((segment == segment[m]) & (np.arange(len(rec.labels)) != m))[0])
    hidden = rec.positions.copy()
    hidden[f - 10 : f + 10, mate] = np.nan
    spiked = hidden.copy()
    spiked[f, m] += spike_mm
    rest = np.ones(len(rec.labels), bool)
    rest[[m, mate]] = False
    for config, trusted in ((FillerConfig(), False), (FillerConfig(outlier_mm=1e12), True)):
        clean, _ = fill_sequence(hidden, rec.labels, rec.rate, config)
        filled, flags = fill_sequence(spiked, rec.labels, rec.rate, config)
        error = np.linalg.norm(filled[f, mate] - rec.true_positions[f, mate])
        if trusted:  # without the outlier test, the spike drags the hidden mate off: what this guards against
            assert error > 100.0, error
            continue
        np.testing.assert_allclose(filled[:, rest], clean[:, rest], atol=1e-6, equal_nan=True)
        assert error < 20.0 and flags[f, m] >= 2 and np.linalg.norm(filled[f, m] - rec.true_positions[f, m]) < 20.0


@pytest.mark.integration
def test_a_ten_frame_spike_does_not_change_the_calibrated_model(tmp_path: Path) -> None:
    """Ten frames of one marker 3 m off (a reflection): calibrate leaves them out and finds the segments and the
    topology of the clean recording; so do the pair spreads alone, which leave out distances so far off
    (``pair_statistics``)."""
    from mocapflow.mocap.calibration import calibrate
    from mocapflow.mocap.clustering import distance_spread
    from mocapflow.mocap.outliers import wild_samples
    from mocapflow.mocap.simulator import SimulatorConfig, simulate

    rec = simulate(SimulatorConfig(rig="human", rate=120, seed=0), 2400)
    spiked = rec.positions.copy()
    spiked[1000:1010, 20] += [3000.0, 0.0, 0.0]
    wild = wild_samples(spiked)
    assert wild.sum() == 10 and wild[1000:1010, 20].all() and not wild_samples(rec.positions).any()

    def model(positions: np.ndarray) -> tuple[list, list]:
        skeleton = calibrate(positions, list(rec.labels), rec.rate)
        return (sorted(tuple(sorted(s.markers)) for s in skeleton.segments),
                sorted((j.parent, j.child) for j in skeleton.joints))

    clean = model(rec.positions)
    assert model(np.where(wild[..., None], np.nan, spiked)) == clean
    assert model(spiked) == clean
    # what the spike does to a plain standard deviation: the marker's most rigid pair, 0.7 mm, spreads by 188 mm
    assert np.sort(distance_spread(spiked, clip=np.inf)[20])[1] > 100 * np.sort(distance_spread(rec.positions)[20])[1]
