"""``mocapflow calibrate IN -o SKELETON.json``: a skeleton (segments, joints, offsets) learnt from a marker file."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from mocapflow.commands import distinct_output, marker_choice, read_chosen
from mocapflow.errors import MocapflowError

if TYPE_CHECKING:
    from mocapflow.mocap.model import Joint, SkeletonModel


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibrate", help="learn a skeleton from labelled marker trajectories (.c3d or .trc)")
    p.add_argument("inputs", nargs="+", metavar="input",
                   help="labelled marker files (.c3d or .trc) of varied motion, one subject with one marker set: "
                        "every trial given is used (a range-of-motion trial locates the joints best: "
                        "calibrate ROM.c3d TRIAL.c3d)")
    p.add_argument("-o", "--output", required=True, help="skeleton file to write (.json)")
    p.add_argument("--segments", type=int, default=None, metavar="K",
                   help="number of segments (default: found from the data)")
    p.add_argument("--method", choices=["rigidity", "spectral", "distance-threshold"], default="rigidity",
                   help="marker clustering: markers rigid within the recording's own noise, joint markers given "
                        "to the segment that needs them (default); spectral (Schoenauer); or a fixed threshold")
    p.add_argument("--joints", choices=["auto", "closed-form", "variance"], default="auto",
                   help="joint estimator: closed-form centre of rotation (Aristidou; more accurate on real skin "
                        "markers), distance variance (Schoenauer), or auto (default): the closed form, found "
                        "down the tree (sphere centres into them) when some segments have only two markers")
    p.add_argument("--name", default=None, help="skeleton name (default: the first input file's stem)")
    marker_choice(p)
    p.set_defaults(func=run)


def summary(skeleton: SkeletonModel) -> str:
    """The segments (with how rigid their markers were), joints (with the motion that located them, how far apart
    their two segments put them and how sure their centres are) and root of a skeleton as aligned text tables, then
    one line per joint the data did not locate, naming the motion it lacked, and what to add for them."""
    lines = [f"{'segment':<16} {'markers':>7} {'rigid mm':>8}  labels"]
    for s in skeleton.segments:
        rigid = f"{s.rigidity_mm:>8.2f}" if s.rigidity_mm is not None else f"{'-':>8}"
        lines.append(f"{s.name:<16} {len(s.markers):>7} {rigid}  {' '.join(s.markers)}")
    lines.append("")
    lines.append(f"{'joint':<32} {'kind':<5} {'motion deg':>10} {'dist mm':>8} {'sd mm':>6} {'gap mm':>6} "
                 f"{'uncert mm':>9}")
    for j in skeleton.joints:
        motion = f"{j.rotation_deg:>10.1f}" if j.rotation_deg is not None else f"{'-':>10}"
        gap = f"{j.gap_mm:>6.1f}" if j.gap_mm is not None else f"{'-':>6}"
        sure = f"{j.uncertainty_mm:>9.0f}" if j.uncertainty_mm is not None else f"{'-':>9}"
        note = "  not located" if j.located is False else ""
        lines.append(f"{j.name:<32} {j.kind:<5} {motion} {j.distance_mean:>8.1f} {j.distance_sd:>6.2f} {gap} "
                     f"{sure}{note}")
    lines.append("")
    lines.append(f"root: {skeleton.root}")
    loose = [not_located(j) for j in skeleton.joints if j.located is False]
    lines.extend(loose)
    if loose:
        lines.append(f"{len(loose)} of {len(skeleton.joints)} joints not located: add a range-of-motion trial (30 deg "
                     "or more of flexion and abduction at each): mocapflow calibrate ROM.c3d TRIAL.c3d")
    return "\n".join(lines)


def not_located(joint: Joint) -> str:
    """One line naming a joint its data did not locate and the motion they lacked."""
    from mocapflow.mocap.calibration import MIN_ROTATION_DEG, UNBOUNDED_MM

    uncertain = (f"its centre could be {joint.uncertainty_mm:.0f} mm off along its weakest direction"
                 if joint.uncertainty_mm is not None and joint.uncertainty_mm < UNBOUNDED_MM else
                 "nothing fixes its centre")
    sd = joint.motion_sd_deg
    if sd is None or sd[0] < MIN_ROTATION_DEG:
        lacked = f"the segments hardly turned relative to each other ({joint.rotation_deg or 0:.1f} deg RMS)"
    else:
        lacked = (f"it turned about one axis ({sd[0]:.0f} deg SD) but only {sd[1]:.0f} and {sd[2]:.0f} deg about "
                  "the other two")
    rule = " (a hinge: placed on its axis level with its neighbours)" if joint.kind == "hinge" else ""
    return f"joint {joint.name} not located{rule}: {uncertain}; {lacked}"


MAX_MARKERS = 500


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from mocapflow.io.markers import join_trials
    from mocapflow.io.skeleton import write_skeleton
    from mocapflow.mocap.calibration import calibrate
    from mocapflow.mocap.compiled import compile_fits
    from mocapflow.mocap.outliers import wild_samples
    from mocapflow.progress import Reporter
    from mocapflow.runtime.kernels import compile_kernels

    if args.segments is not None and args.segments < 2:
        raise MocapflowError("--segments must be at least 2")
    out = distinct_output(args.output, *args.inputs)
    data = join_trials([read_chosen(path, args) for path in args.inputs])
    if data.n_markers > MAX_MARKERS:
        raise MocapflowError(f"{data.n_markers} markers: calibrate takes at most {MAX_MARKERS} (its memory grows with "
                             "the square of their number); choose a subject's markers with --markers/--exclude")
    wild = wild_samples(data.positions)
    if wild.any():  # a reflection a few frames long must not decide which markers move together
        print(f"{int(wild.sum())} wild samples (a metre or more from their marker's neighbourhood in time) left out")
        data.positions = np.where(wild[..., None], np.nan, data.positions)
    compile_kernels(sys.stderr, compile_fits)  # the input is read and checked: the work is to be done
    start = time.perf_counter()
    skeleton = calibrate(data.positions, data.labels, data.rate, segments=args.segments, method=args.method,
                         joint_method=args.joints, name=args.name or Path(args.inputs[0]).stem, progress=Reporter())
    elapsed = time.perf_counter() - start
    write_skeleton(out, skeleton)
    print(summary(skeleton))
    trials = f" of {len(args.inputs)} trials" if len(args.inputs) > 1 else ""
    print(f"wrote {out}: {len(skeleton.segments)} segments, {len(skeleton.joints)} joints from "
          f"{data.n_frames} frames{trials} in {elapsed:.1f} s")
    return 0
