"""``mocapflow label IN -o OUT``: unlabelled point clouds to labelled marker trajectories."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

import numpy as np

from mocapflow.commands import distinct_output, marker_choice, read_chosen, settings
from mocapflow.errors import MocapflowError

if TYPE_CHECKING:
    from mocapflow.mocap.labelling import LabellerConfig


FEW_FIT = 0.8
"""Below this share of the points named from a skeleton, the command says the skeleton may not fit the capture."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("label", help="give every marker of an unlabelled C3D/TRC capture one persistent label")
    p.add_argument("input", help="C3D or TRC file of unlabelled points (slot order meaningless from frame to frame)")
    p.add_argument("-o", "--output", required=True, help="labelled .c3d or .trc file to write")
    p.add_argument("--gate", type=float, metavar="MM", help="largest frame-to-frame prediction error (default 30)")
    p.add_argument("--reid-gate", type=float, metavar="MM",
                   help="largest error when a lost marker is found again from its neighbours (default 30)")
    p.add_argument("--confirm", type=int, metavar="FRAMES",
                   help="frames a new point must live to count as a marker, not a ghost (default 5)")
    p.add_argument("--markers", type=int, metavar="N", help="number of physical markers, when known")
    p.add_argument("--skeleton", metavar="SKELETON.json",
                   help="name every point with this skeleton's marker names by fitting its segments' marker layouts "
                        "(a skeleton from mocapflow calibrate on a labelled trial of the same subject)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="any other labeller setting, e.g. --set max_coast_s=0.2 (see mocapflow.mocap.labelling)")
    marker_choice(p, include=False)
    p.set_defaults(func=run)


def _config(args: argparse.Namespace) -> LabellerConfig:
    """LabellerConfig from the options; a bad value is a one-line error naming the setting."""
    from mocapflow.mocap.labelling import LabellerConfig

    config = settings(LabellerConfig, args.overrides, gate_mm=args.gate, reid_gate_mm=args.reid_gate,
                      offline_confirm_frames=args.confirm, expected_markers=args.markers)
    if "confirm_frames" in config.model_fields_set:
        raise MocapflowError("--set confirm_frames: that is a live stream's wait; a file is labelled offline, which "
                             "waits --confirm frames (offline_confirm_frames)")
    return config


def run(args: argparse.Namespace) -> int:
    from mocapflow.io.markers import MarkerData, write_markers
    from mocapflow.mocap.compiled import compile_fits, compile_labelling, compile_model_labelling
    from mocapflow.mocap.labelling import label_sequence
    from mocapflow.progress import Reporter, progress
    from mocapflow.runtime.kernels import compile_kernels

    config = _config(args)
    out = distinct_output(args.output, args.input)
    data = read_chosen(args.input, args)
    points = data.positions
    if not np.isfinite(points).all(axis=2).any():
        raise MocapflowError(f"{args.input}: no points to label")
    stages = (compile_labelling,) if args.skeleton is None else (compile_fits, compile_model_labelling)
    compile_kernels(sys.stderr, *stages)  # the input is read and checked: the work is to be done
    if args.skeleton is not None:
        from mocapflow.io.skeleton import read_skeleton
        from mocapflow.mocap.labelling.model import label_with_skeleton

        skeleton = read_skeleton(args.skeleton)
        try:
            tracks, labels = label_with_skeleton(points, data.rate, skeleton, report=Reporter())
        except ValueError as exc:
            raise MocapflowError(f"{args.skeleton}: {exc}") from None
    else:
        tracks, labels = label_sequence(progress(points, len(points), "label"), data.rate, config, Reporter())
    if not labels:
        raise MocapflowError(f"{args.input}: no point lived long enough to be a marker (see --confirm)")
    write_markers(out, MarkerData(positions=tracks, labels=labels, rate=data.rate, first_frame=data.first_frame))
    given = int(np.isfinite(points).all(axis=2).sum())
    kept = int(np.isfinite(tracks).all(axis=2).sum())
    print(f"wrote {out}: {len(labels)} markers over {len(tracks)} frames at {data.rate:g} Hz; "
          f"{kept}/{given} points labelled ({100.0 * kept / given:.2f} %), the rest dropped as ghosts"
          f"{' or markers the skeleton does not know' if args.skeleton else ''}")
    if args.skeleton and kept < FEW_FIT * given:
        print(f"only {100.0 * kept / given:.0f} % of the points fit the segments of {args.skeleton}: is it this "
              "subject's skeleton, with this marker set, calibrated on a trial that moved every joint? (mocapflow "
              "calibrate says how sure each segment and joint is)", file=sys.stderr)
    return 0
