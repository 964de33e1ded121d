"""``mocapflow simulate -o FILE.c3d``: the simulator's frames to a C3D file, with ground truth beside it."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.commands import distinct_output, settings
from mocapflow.errors import MocapflowError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help="write simulated capture to C3D/TRC, with a .truth.npz sidecar: ground truth, "
                       "and the single-camera rays when cameras are modelled")
    p.add_argument("-o", "--output", required=True, help="output .c3d or .trc file")
    p.add_argument("--frames", type=int, default=2400, help=f"number of frames (default 2400, at most {MAX_FRAMES:,})")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="simulator setting, e.g. --set rig=rods --set cameras=4 (see `mocapflow plugins simulator`)")
    p.set_defaults(func=run)


MAX_FRAMES = 1_000_000
"""About 70 minutes at 240 Hz: what a C3D file written from memory can hold."""


def truth_path(path: Path) -> Path:
    return path.with_suffix(".truth.npz")


def run(args: argparse.Namespace) -> int:

    from mocapflow.errors import MocapFileError, MotionError
    from mocapflow.io.bvh import read_bvh
    from mocapflow.io.markers import MarkerData, write_markers
    from mocapflow.mocap.simulator import SimulatorConfig, simulate
    from mocapflow.progress import Reporter

    config = settings(SimulatorConfig, args.overrides)
    if not 1 <= args.frames <= MAX_FRAMES:
        raise MocapflowError(f"--frames {args.frames}: must be between 1 and {MAX_FRAMES:,}")
    out = distinct_output(args.output, config.bvh or "")
    try:
        rec = simulate(config, args.frames, read_bvh(config.bvh) if config.bvh else None, progress=Reporter())
    except MotionError as exc:
        raise MocapFileError(f"{config.bvh}: {exc}") from None
    truth: dict[str, Any] = {
        "labels": np.array(rec.labels), "true_positions": rec.true_positions, "visible": rec.visible,
        "joint_names": np.array(rec.joint_names), "joint_centres": rec.joint_centres,
        "joint_parent": np.array(rec.joint_parent), "joint_child": np.array(rec.joint_child),
        "marker_segment": np.array(rec.marker_segment), "rate": np.array(rec.rate),
    }
    if rec.rays is not None:  # a C3D file has no place for them
        truth["rays"] = rec.rays
    if rec.points is not None and rec.identity is not None:
        width = max(len(p) for p in rec.points)
        positions = np.full((args.frames, width, 3), np.nan)
        identity = np.full((args.frames, width), -1, np.int32)
        for i, (pts, ids) in enumerate(zip(rec.points, rec.identity, strict=True)):
            positions[i, : len(pts)] = pts
            identity[i, : len(ids)] = ids
        labels = [f"P{i + 1:03d}" for i in range(width)]
        truth["identity"] = identity
    else:
        positions, labels = rec.positions, rec.labels
    write_markers(out, MarkerData(positions=positions, labels=labels, rate=rec.rate))
    np.savez_compressed(truth_path(out), **truth)
    kind = "unlabelled points" if rec.points is not None else "labelled markers"
    print(f"wrote {out} ({args.frames} frames at {rec.rate:g} Hz, {len(labels)} {kind}) and {truth_path(out)}")
    return 0
