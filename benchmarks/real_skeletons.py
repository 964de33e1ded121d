"""Skeletons of the real full-body recordings checked against anatomy, with no option given.

Run: python benchmarks/real_skeletons.py [FILE ...]. For every real file in ../shared/data (or the ones named) it
calibrates with the defaults, solves, and prints one row of checks: no segment mixes two limbs or a leg and the
trunk, each limb is one chain hanging from the body by one joint, each leg has at least thigh, shank and foot, and
the mean marker fit, and what the pose solve costs per frame (median CPU microseconds, the solver compiled once as the
live skeleton node keeps it) on batches of 1, 10 and 1000 frames (fewer when the file is shorter). The marker-name
-> body-region maps below are the checks' truth only; calibration never sees them.
tests/test_real_skeletons.py runs the same checks.
"""

from __future__ import annotations

import argparse
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import _common
import numpy as np

from mocapflow.io.markers import read_markers
from mocapflow.mocap.calibration import calibrate
from mocapflow.mocap.model import SkeletonModel
from mocapflow.mocap.solve import PoseSolver, solve

FILES = ("cmu_85_02.c3d", "cmu_85_12_breakdance.c3d", "cmu_02_05.c3d", "cmu_dribble_shoot_basketball.c3d",
         "hamner_run200.trc", "sprinter_JA1Gait35.c3d", "lowerbody_clusters_knee_0401.c3d")

TRUNK = "trunk"
LIMBS = ("left arm", "right arm", "left leg", "right leg")
_SIDED = {  # marker name without its side letter -> limb kind, for the CMU, Hamner, sprinter and lower-body sets
    "arm": {"UPA", "ELB", "FRM", "WRA", "WRB", "FIN", "UA1", "UA2", "UA3", "LEL", "MEL", "FAradius", "FAsuperior",
            "FAulna", "ARM", "FOREARM", "WR"},
    "leg": {"THI", "KNE", "SHN", "ANK", "HEE", "TOE", "MT5", "TH1", "TH2", "TH3", "TH4", "TB1", "TB2", "TB3", "CAL",
            "THLP", "THLD", "THAP", "THAD", "LEPI", "PAT", "TIAP", "TIAD", "TILAT", "LMAL", "HEEL", "MFS", "MFL",
            "P1MT", "P5MT", "MKN", "LKN", "SH1", "SH2", "SH3", "SH4", "LAK", "MAK", "CUN"},
}
_UNNAMED = {"*52": "right arm", "*53": "left arm"}  # the sprinter's two unnamed wrist points


def region(label: str) -> str:
    """Body region of a marker label: the trunk (pelvis, spine, head, shoulders) or one of the four limbs."""
    name = label.split(":")[-1]
    if name in _UNNAMED:
        return _UNNAMED[name]
    side = {"L": "left", "R": "right"}.get(name[:1])
    for kind, names in _SIDED.items():
        if side and name[1:] in names:
            return f"{side} {kind}"
    return TRUNK


@dataclass
class Checks:
    """The anatomical checks of one calibrated skeleton."""

    mixed: list[str]  # segments holding markers of two limbs, or of a leg and the trunk
    not_chains: list[str]  # limbs whose segments are not one chain hanging from the body by one joint
    short_legs: list[str]  # legs with fewer than three segments (thigh, shank, foot)
    fit_mm: float  # mean marker fit of the solve: mean distance between fitted and observed markers
    segment_rms_mm: float  # the solve's per-segment RMS residual, averaged over frames and segments

    @property
    def ok(self) -> bool:
        return not (self.mixed or self.not_chains or self.short_legs) and self.fit_mm < 10.0


def check(skeleton: SkeletonModel, positions: np.ndarray, labels: Sequence[str]) -> Checks:
    """Anatomical checks of a skeleton calibrated from (F, N, 3) labelled trajectories."""
    limb_of: dict[str, str] = {}
    mixed = []
    for s in skeleton.segments:
        regions = {region(m) for m in s.markers}
        limbs = regions - {TRUNK}
        if len(limbs) > 1 or (TRUNK in regions and any("leg" in r for r in limbs)):
            mixed.append(f"{s.name}({' '.join(m.split(':')[-1] for m in s.markers)})")
        limb_of[s.name] = limbs.pop() if len(limbs) == 1 else TRUNK
    parent = {j.child: j.parent for j in skeleton.joints}
    not_chains, short_legs = [], []
    present = {r for r in limb_of.values()}
    for limb in LIMBS:
        if limb not in present:
            continue
        members = [s for s, r in limb_of.items() if r == limb]
        tops = [s for s in members if limb_of.get(parent.get(s, ""), TRUNK) != limb]
        children = {s: [c for c, p in parent.items() if p == s] for s in members}
        branching = any(len([c for c in children[s] if limb_of[c] == limb]) > 1 for s in members)
        foreign = any(limb_of[c] != limb for s in members for c in children[s])
        hangs = len(tops) == 1 and tops[0] != skeleton.root
        if not hangs or branching or foreign:
            not_chains.append(limb)
        if "leg" in limb and len(members) < 3:
            short_legs.append(f"{limb}: {len(members)}")
    pose = solve(skeleton, positions, labels)
    return Checks(mixed, not_chains, short_legs, pose.marker_fit, float(np.nanmean(pose.residual)))


def solve_cost(skeleton: SkeletonModel, positions: np.ndarray, labels: Sequence[str],
               batches: Sequence[int] = (1, 10, 1000), calls: int = 200) -> list[float]:
    """Median CPU cost of the pose solve per frame (us) for each batch size, over up to ``calls`` consecutive
    batches (at least three) from the start of the (F, N, 3) trajectories."""
    solver = PoseSolver(skeleton, labels)
    costs = []
    for size in batches:
        size = min(size, len(positions))
        times = []
        for i in range(max(3, min(calls, calls * 10 // size))):
            batch = positions[i * size % (len(positions) - size + 1):][:size]
            times.append(_common.timed(solver, batch)[1])
        costs.append(float(np.median(times)) / size * 1e6)
    return costs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("files", nargs="*", default=[str(_common.DATA / f) for f in FILES])
    parser.add_argument("-v", "--verbose", action="store_true", help="print each skeleton's segments and joints")
    args = parser.parse_args()
    print("| file | segments | joints | mixed segments | limbs not one chain | legs under 3 segments | fit mm "
          "| segment RMS mm | s | solve us/frame, 1 / 10 / 1000 frames |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for path in args.files:
        data = read_markers(path)
        start = time.perf_counter()
        try:
            skeleton = calibrate(data.positions, data.labels, data.rate)
        except Exception as exc:  # a failure is a row of the table
            print(f"| {Path(path).name} | error: {re.sub(r'[|]', '/', str(exc))} |")
            continue
        seconds = time.perf_counter() - start
        c = check(skeleton, data.positions, data.labels)
        cost = " / ".join(f"{us:.0f}" for us in solve_cost(skeleton, data.positions, data.labels))
        print(f"| {Path(path).name} | {len(skeleton.segments)} | {len(skeleton.joints)} | {', '.join(c.mixed) or '-'}"
              f" | {', '.join(c.not_chains) or '-'} | {', '.join(c.short_legs) or '-'} | {c.fit_mm:.2f} | "
              f"{c.segment_rms_mm:.2f} | {seconds:.1f} | {cost} |")
        if args.verbose:
            for s in skeleton.segments:
                print(f"    {s.name:12s} {' '.join(m.split(':')[-1] for m in s.markers)}")
            for j in skeleton.joints:
                print(f"    {j.parent:>12s} -> {j.child:12s} {j.kind} cost {j.cost:.2f} dist {j.distance_mean:.0f}")


if __name__ == "__main__":
    main()
