"""Labelling benchmark: accuracy against truth under mild damage, stress and still ghosts, and the labeller's cost.

Three sets of cases, identities stripped, occlusions and ghosts added, rows shuffled every frame (``unlabel``):

- mild: the quickstart graph's simulated stream (deployments/quickstart.yaml), the simulator's human rig at 240 Hz at
  a moderate and a heavy level of damage, seen directly and through the simulator's camera model (4 and 8 cameras),
  and three real captures;
- stress: ordinary but harsh capture conditions, on every labelled real capture of the shared data folder and on the
  simulated human and quadruped: each marker hidden in independent gaps of 0.2-2 s, a third of the time from the first
  frame on (``stationary``: gaps under way at the start too), and a one-frame ghost in about a fifth of the frames;
- ghosts: the stress captures (600 frames) with still ghosts that live up to 20 frames, longer than a new track
  needs to be believed (0.3 new a frame).

For each case it prints the cost of ``Labeller.update`` per frame (mean, median, 99th percentile, in microseconds of
wall time: a busy machine inflates them), then for the streaming labels (which leave a new track's first
``confirm_frames`` frames unlabelled) and the offline ``label_sequence`` (those frames filled in, fragments merged,
short tracks dropped): right identity (share of true points on the track that stands for their marker), swaps, output
tracks per true marker and the share of true points left unlabelled, and of it the share from before their marker was
first labelled at all (a streaming labeller that tells a marker from a ghost by how long it lives cannot name a marker's
first frames). Stress cases are labelled whole without a model, and also from a skeleton calibrated on an undamaged
trial of the same subject (the simulated rigs: another trial; a real capture: its first half, the second half of the
damaged capture being named), streaming (``TrackedModelLabeller``, as the ``labeller-skeleton`` node) and offline
(``label_with_skeleton``, forward and backward, then by trajectory): the share of true points named with their own
marker's name, and of those of the markers the skeleton has (a marker alone on its segment is left out of it).

    python benchmarks/labelling.py [--cases mild|stress|ghosts|all] [--quick] [--data DIR]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import _common
import numpy as np
import yaml

from mocapflow.mocap.calibration import CalibrationError, calibrate
from mocapflow.mocap.evaluation import STRESS, LabellingScore, score_labelling, score_naming, unlabel
from mocapflow.mocap.labelling import Labeller, LabellerConfig, label_sequence
from mocapflow.mocap.labelling.model import TrackedModelLabeller, label_with_skeleton
from mocapflow.mocap.model import SkeletonModel
from mocapflow.mocap.simulator import SimulatorConfig, simulate

# mild damage levels: simulator settings, and unlabel() settings (occlusions per marker per second, ghosts per frame)
LEVELS = {
    "moderate": ({"dropout_rate": 0.2, "long_gaps": 2.0, "ghosts": 2.0}, (0.05, 1.0)),
    "heavy": ({"dropout_rate": 0.5, "long_gaps": 4.0, "ghosts": 5.0}, (0.2, 3.0)),
}
CAMERAS = (4, 8)  # camera counts of the camera-model cases
STRESS_RIGS = (("human", 120.0), ("quadruped", 120.0))
# still ghosts (a reflection, a lamp) living up to 20 frames, longer than a new track needs to be believed, 0.3 new a
# frame, with gaps as the mild damage's; 600 frames of each stress capture
GHOSTS = {"gaps_per_s": 0.3, "long_fraction": 0.5, "ghosts": 0.3, "ghost_frames": 20}
GHOST_FRAMES = 600

Case = tuple[str, list[np.ndarray], list[np.ndarray], float, int]  # name, points, identity, rate, true marker count


def _quickstart(frames: int) -> Case:
    """The stream of the quickstart graph's tracker (deployments/quickstart.yaml): the simulated human with its
    ghosts and gaps, whose cost per frame the live graph's budget is set for."""
    graph = yaml.safe_load((_common.ROOT / "deployments" / "quickstart.yaml").read_text())
    rec = simulate(SimulatorConfig(**{"seed": 7, **graph["nodes"]["tracker"]["config"]}), frames)
    assert rec.points is not None and rec.identity is not None
    return f"quickstart stream, simulated human {rec.rate:g} Hz", rec.points, rec.identity, rec.rate, len(rec.labels)


def _mild(frames: int, data: Path) -> list[Case]:
    cases = [_quickstart(frames)]
    simulated = [(level, damage, 0) for level, (damage, _) in LEVELS.items()]
    simulated += [("moderate", LEVELS["moderate"][0], cameras) for cameras in CAMERAS]
    for level, damage, cameras in simulated:
        rec = simulate(SimulatorConfig(rig="human", rate=240, noise_mm=0.5, unlabelled=True, seed=7, cameras=cameras,
                                       **damage), frames)
        assert rec.points is not None and rec.identity is not None
        seen_by = f"{cameras} cameras, " if cameras else ""
        cases.append((f"simulated human 240 Hz, {seen_by}{level}", rec.points, rec.identity, rec.rate,
                      len(rec.labels)))
    if not data.is_dir():
        print(f"(real captures skipped: {data} is absent)")
        return cases
    from mocapflow.io.markers import read_markers

    for name in ("lowerbody_clusters_knee_0401.c3d", "cmu_85_02.c3d", "cmu_85_12_breakdance.c3d"):
        marker_data = read_markers(data / name)
        for level, (_, (dropouts, ghosts)) in LEVELS.items():
            points, identity = unlabel(marker_data.positions[:frames], marker_data.rate, seed=1,
                                       gaps_per_s=dropouts, ghosts=ghosts)
            cases.append((f"{name} {marker_data.rate:g} Hz, {level}", list(points), list(identity),
                          marker_data.rate, marker_data.n_markers))
    return cases


def stress_captures(frames: int, data: Path) -> list[tuple[str, np.ndarray, list[str], float]]:
    """(name, labelled positions (F, N, 3), labels, rate) of the stress cases before damage: the simulated rigs and
    every labelled real capture in ``data``."""
    out = []
    for rig, rate in STRESS_RIGS:
        rec = simulate(SimulatorConfig(rig=rig, rate=rate, noise_mm=0.5, seed=7), frames)
        out.append((f"simulated {rig} {rate:g} Hz", rec.positions, rec.labels, rec.rate))
    if not data.is_dir():
        print(f"(real captures skipped: {data} is absent)")
        return out
    from mocapflow.io.markers import read_markers

    for path in sorted(data.iterdir()):
        if path.suffix.lower() in (".c3d", ".trc"):
            md = read_markers(path)
            out.append((f"{path.name} {md.rate:g} Hz", md.positions[:frames], md.labels, md.rate))
    return out


def _stress(frames: int, data: Path) -> list[tuple[Case, SkeletonModel | None, list[str], int]]:
    """The stress cases (whole), each with a skeleton calibrated on the undamaged first half of its capture (the
    simulated rigs: on another trial of the same subject), its true marker labels, and the first frame the skeleton
    names (a real capture's second half; 0 for the simulated rigs)."""
    cases = []
    for name, positions, labels, rate in stress_captures(frames, data):
        if name.startswith("simulated"):
            rig = name.split()[1]
            reference, named = simulate(SimulatorConfig(rig=rig, rate=rate, noise_mm=0.5, seed=3), frames).positions, 0
        else:
            reference, named = positions[: len(positions) // 2], len(positions) // 2
        try:
            skeleton = calibrate(reference, labels, rate)
        except CalibrationError as exc:
            print(f"(no skeleton for {name}: {exc})")
            skeleton = None
        points, identity = unlabel(positions, rate, seed=1, stationary=True, **STRESS)
        cases.append(((f"{name}, stress", list(points), list(identity), rate, len(labels)), skeleton, labels, named))
    return cases


def _ghosts(data: Path) -> list[Case]:
    """The stress captures under still, long-lived ghosts (``GHOSTS``)."""
    cases = []
    for name, positions, labels, rate in stress_captures(GHOST_FRAMES, data):
        points, identity = unlabel(positions, rate, seed=2, **GHOSTS)  # type: ignore[arg-type]
        cases.append((f"{name}, ghosts up to {GHOSTS['ghost_frames']} frames", list(points), list(identity), rate,
                      len(labels)))
    return cases


def _named(skeleton: SkeletonModel, points: list[np.ndarray], identity: list[np.ndarray], rate: float,
           labels: list[str], streaming: bool = False) -> tuple[float, float, float, float]:
    """Shares of true points that ``label_with_skeleton`` (or, ``streaming``, ``TrackedModelLabeller`` frame by frame,
    as the ``labeller-skeleton`` node runs it) names with their own marker's name and with another's; the share of
    the true points of the markers the skeleton has (a marker alone on its segment has no layout) named with their
    own name; and its cost per frame (us, wall time)."""
    start = time.perf_counter()
    if streaming:
        labeller = TrackedModelLabeller(skeleton, rate)
        named, names = np.stack([labeller.update(p, i / rate)[0] for i, p in enumerate(points)]), labeller.labels
    else:
        named, names = label_with_skeleton(points, rate, skeleton)
    cost = (time.perf_counter() - start) / len(points) * 1e6
    score = score_naming(named, names, points, identity, labels)
    return score.right / score.total, score.wrong / score.total, score.right / score.known, cost


def stream_labels(points: list[np.ndarray], rate: float) -> tuple[np.ndarray, np.ndarray]:
    """Streaming labels (F, T, 3) and the wall time of each ``update`` call (s)."""
    labeller = Labeller(LabellerConfig(), rate)
    rows, cost = [], np.empty(len(points))
    for i, frame in enumerate(points):
        start = time.perf_counter()
        result = labeller.update(frame, i / rate)
        cost[i] = time.perf_counter() - start
        rows.append(result.positions)
    tracks = np.full((len(rows), len(labeller.labels), 3), np.nan)
    for i, row in enumerate(rows):
        tracks[i, : len(row)] = row
    return tracks, cost


def _line(score: LabellingScore) -> str:
    return (f"right identity {100 * score.accuracy:7.3f} %, swaps {score.swaps:3d}, "
            f"{score.tracks / score.markers_true:.2f} tracks per marker ({score.ghost_tracks} ghost tracks), "
            f"{100 * (1 - score.assigned):.2f} % of true points unlabelled "
            f"({100 * score.unlabelled_at_first:.2f} % before their marker's first label)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", choices=("mild", "stress", "ghosts", "all"), default="all",
                        help="which cases (default all)")
    parser.add_argument("--quick", action="store_true", help="at most 1500 frames per case (default 4800 simulated, "
                        "real captures whole)")
    parser.add_argument("--data", type=Path, default=_common.DATA, help="folder of the real captures")
    args = parser.parse_args()
    frames = 1500 if args.quick else 4800
    cases: list[tuple[Case, SkeletonModel | None, list[str], int]] = []
    if args.cases in ("mild", "all"):
        cases += [(case, None, [], 0) for case in _mild(frames, args.data)]
    if args.cases in ("stress", "all"):
        cases += _stress(frames, args.data)
    if args.cases in ("ghosts", "all"):
        cases += [(case, None, [], 0) for case in _ghosts(args.data)]
    for (name, points, identity, rate, markers), skeleton, labels, named in cases:
        seen = np.mean([np.isfinite(np.asarray(p)).all(axis=1).sum() for p in points])
        tracks, cost = stream_labels(points, rate)
        start = time.perf_counter()
        offline, _ = label_sequence(points, rate)
        offline_s = time.perf_counter() - start
        us = cost * 1e6
        print(f"\n{name}: {len(points)} frames, {markers} markers, {seen:.1f} points per frame")
        print(f"  update cost: mean {us.mean():.0f} us, median {np.median(us):.0f} us, "
              f"p99 {np.percentile(us, 99):.0f} us; offline label_sequence {offline_s / len(points) * 1e6:.0f} us "
              "per frame")
        print(f"  streaming: {_line(score_labelling(tracks, points, identity, markers))}")
        print(f"  offline:   {_line(score_labelling(offline, points, identity, markers))}", flush=True)
        for streaming in (True, False) if skeleton is not None else ():
            right, wrong, of_known, named_us = _named(skeleton, points[named:], identity[named:], rate, labels,
                                                      streaming)
            frames_named = f" (frames {named}-{len(points) - 1})" if named else ""
            print(f"  skeleton, {'streaming' if streaming else 'offline'}{frames_named}: {100 * right:.3f} % of true "
                  f"points carry their own marker's name, {100 * wrong:.3f} % another's, "
                  f"{100 * max(1 - right - wrong, 0.0):.3f} % none; {100 * of_known:.3f} % of those of the skeleton's "
                  f"markers ({named_us:.0f} us per frame)", flush=True)


if __name__ == "__main__":
    main()
