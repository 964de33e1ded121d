"""``mocapflow fill IN -o OUT [--skeleton SKELETON.json] [--offline]``: fill marker gaps frame by frame, exactly as
the live filler would (it never looks ahead), or with ``--offline`` both ways through the file (the frames after
each gap used too), and record in the output's flags how each sample was obtained."""

from __future__ import annotations

import argparse
import sys
import zipfile
from pathlib import Path

import numpy as np

from mocapflow.commands import distinct_output, marker_choice, read_chosen, settings
from mocapflow.errors import MocapflowError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fill", help="fill occluded markers with the real-time Kalman and rigid-body filler")
    p.add_argument("input", help="labelled marker file (.c3d or .trc)")
    p.add_argument("-o", "--output", required=True, help="filled marker file (.c3d or .trc): same labels and order")
    p.add_argument("--skeleton", help="skeleton (.json, from `mocapflow calibrate`); without one, segments, shapes "
                                      "and joints are learned from the frames seen so far")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="filler setting, e.g. --set joint_anchors=hidden (fields of FillerConfig)")
    p.add_argument("--rays", metavar="FILE.npz",
                   help="single-camera rays per frame and marker: the array 'rays' (frames x markers x 6: origin mm, "
                        "direction; NaN where none) of an .npz file, such as the sidecar `mocapflow simulate` writes")
    p.add_argument("--offline", action="store_true",
                   help="use the frames on both sides of every gap: the filler run forwards and backwards, blended "
                        "across each gap (every marker seen once is filled everywhere); not what a live stream gets")
    p.add_argument("--joints", action="store_true",
                   help="also write the skeleton's joint centres, tracked through occlusions, as extra points")
    marker_choice(p)
    p.set_defaults(func=run)


def read_rays(path: str, shape: tuple[int, int]) -> np.ndarray:
    """The 'rays' array of an .npz file, checked against the recording's (frames, markers)."""
    if not Path(path).is_file():
        raise MocapflowError(f"{path}: no such file")
    if not zipfile.is_zipfile(path):
        raise MocapflowError(f"{path}: not an .npz file (a zip archive of named arrays)")
    try:
        with np.load(path, allow_pickle=False) as archive:
            if "rays" not in archive.files:
                raise MocapflowError(f"{path}: no 'rays' array (arrays: {', '.join(archive.files) or 'none'})")
            rays = np.asarray(archive["rays"], dtype=float)
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise MocapflowError(f"{path}: unreadable rays ({exc})") from exc
    if rays.shape != (*shape, 6):
        raise MocapflowError(f"{path}: rays are {' x '.join(map(str, rays.shape))}, the recording needs "
                             f"{shape[0]} x {shape[1]} x 6 (frames x markers x origin and direction)")
    return rays


def run(args: argparse.Namespace) -> int:
    from mocapflow.io.markers import MarkerData, write_markers
    from mocapflow.io.skeleton import read_skeleton
    from mocapflow.mocap.compiled import compile_filling
    from mocapflow.mocap.filling import FillCase, FillerConfig, fill_both_ways, fill_recording
    from mocapflow.progress import Reporter
    from mocapflow.runtime.kernels import compile_kernels

    out = distinct_output(args.output, args.input)
    if out.suffix.lower() not in (".c3d", ".trc"):
        raise MocapflowError(f"{out}: output must be .c3d or .trc")
    config = settings(FillerConfig, args.overrides)
    skeleton = read_skeleton(args.skeleton) if args.skeleton else None
    if args.joints and skeleton is None:
        raise MocapflowError("--joints needs --skeleton: learned joints come and go while they are learned")
    data = read_chosen(args.input, args)
    if skeleton is not None and not {m for s in skeleton.segments for m in s.markers} & set(data.labels):
        raise MocapflowError(f"{args.input}: none of the skeleton's markers is in the file")

    rays = read_rays(args.rays, data.positions.shape[:2]) if args.rays else None

    compile_kernels(sys.stderr, compile_filling)  # the input is read and checked: the work is to be done
    joints = [j.name for j in skeleton.joints] if args.joints and skeleton is not None else []
    fill = fill_both_ways if args.offline else fill_recording
    positions, flags, centres = fill(data.positions, data.labels, data.rate, config, skeleton, rays=rays,
                                               joints=joints, progress=Reporter())

    extra = dict(data.extra)
    for name, track in centres.items():
        extra[name if name not in data.labels else f"joint_{name}"] = track
    write_markers(out, MarkerData(positions=positions, labels=data.labels, rate=data.rate,
                                  first_frame=data.first_frame, flags=flags, extra=extra))
    counts = np.bincount(flags.ravel(), minlength=len(FillCase))
    seen = np.isfinite(data.positions).all(-1)
    missing_before = int((~seen).sum())
    filled = ", ".join(f"{case.name.lower().replace('_', ' ')} {counts[case]}" for case in FillCase
                       if case > FillCase.OBSERVED and counts[case])
    print(f"wrote {out}: {data.n_frames} frames, {data.n_markers} markers; {missing_before} missing samples, "
          f"{missing_before - counts[FillCase.MISSING]} filled ({filled or 'none'}), "
          f"{counts[FillCase.MISSING]} left missing")
    left = (flags == FillCase.MISSING).sum(axis=0)
    most = [int(i) for i in np.argsort(-left, kind="stable")[:3] if left[i]]
    if most:  # where they lie, and how often each of those markers was seen
        print("most left missing: " + ", ".join(f"{data.labels[i]} {left[i]} (seen in {seen[:, i].sum()} frames)"
                                                for i in most))
    # a stream has nothing to place a marker by before it is first seen; the frames after it do
    early = int(((flags == FillCase.MISSING) & (np.cumsum(seen, axis=0) == 0) & seen.any(axis=0)).sum())
    if early and not args.offline:
        print(f"{early} of those left missing lie before their marker was first seen: --offline fills them from the "
              "frames after")
    return 0
