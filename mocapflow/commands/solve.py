"""``mocapflow solve IN --skeleton SKELETON.json -o OUT``: joint centres and segment rotations in every frame, written
as marker points (.c3d/.trc), per-frame JSON, or a BVH animation (.bvh) for animation tools."""

from __future__ import annotations

import argparse
import sys

import numpy as np

from mocapflow.commands import distinct_output, marker_choice, read_chosen
from mocapflow.errors import MocapflowError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("solve", help="fit a calibrated skeleton to every frame of a marker file")
    p.add_argument("input", help="labelled marker file (.c3d or .trc)")
    p.add_argument("--skeleton", required=True, help="skeleton written by `mocapflow calibrate` (.json)")
    p.add_argument("-o", "--output", required=True,
                   help="output: .c3d/.trc (input markers plus one point per joint), .json (per-frame joint "
                        "centres and segment poses) or .bvh (the skeleton's animation)")
    p.add_argument("--bvh-order", default="ZXY", choices=["ZXY", "XYZ", "ZYX", "YXZ", "XZY", "YZX"],
                   help="Euler order of the BVH rotation channels (default ZXY)")
    marker_choice(p)
    p.set_defaults(func=run)


def _rows(values: np.ndarray) -> list:
    """(F, K, D) floats as nested lists with null for rows holding a NaN."""
    rounded = np.round(values, 4)
    known = np.asarray(np.isfinite(rounded).all(-1))
    return [[row.tolist() if ok else None for row, ok in zip(frame, oks, strict=True)]
            for frame, oks in zip(rounded, known, strict=True)]


def run(args: argparse.Namespace) -> int:
    import orjson

    from mocapflow.io.bvh import skeleton_bvh, write_bvh
    from mocapflow.io.markers import MarkerData, write_markers
    from mocapflow.io.skeleton import read_skeleton
    from mocapflow.mocap.compiled import compile_fits
    from mocapflow.mocap.solve import solve
    from mocapflow.progress import Reporter
    from mocapflow.runtime.kernels import compile_kernels

    out = distinct_output(args.output, args.input, args.skeleton)
    if out.suffix.lower() not in (".c3d", ".trc", ".json", ".bvh"):
        raise MocapflowError(f"{out}: output must be .c3d, .trc, .json or .bvh")
    skeleton = read_skeleton(args.skeleton)
    data = read_chosen(args.input, args)
    missing = sorted({m for s in skeleton.segments for m in s.markers} - set(data.labels))
    if len(missing) == sum(len(s.markers) for s in skeleton.segments):
        raise MocapflowError(f"{args.input}: none of the skeleton's markers is in the file")
    compile_kernels(sys.stderr, compile_fits)  # the input is read and checked: the work is to be done
    try:
        pose = solve(skeleton, data.positions, data.labels, progress=Reporter())
    except ValueError as exc:
        raise MocapflowError(f"{args.skeleton}: {exc}") from None
    if out.suffix.lower() == ".json":
        document = {
            "skeleton": skeleton.name, "rate": data.rate, "first_frame": data.first_frame, "units": "mm",
            "joints": pose.joint_names, "segments": pose.segment_names,
            "parents": [pose.segment_names[p] if p >= 0 else None for p in pose.parents],
            "frames": [
                {"frame": data.first_frame + i, "joint_centres": centres, "rotations": rotations,
                 "translations": translations}
                for i, (centres, rotations, translations) in enumerate(zip(
                    _rows(pose.joint_centres), _rows(pose.rotations), _rows(pose.translations), strict=True))
            ],
        }
        out.write_bytes(orjson.dumps(document))
    elif out.suffix.lower() == ".bvh":
        try:
            write_bvh(out, skeleton_bvh(skeleton, pose, data.rate, args.bvh_order))
        except ValueError as exc:
            raise MocapflowError(f"{args.skeleton}: cannot be written as BVH: {exc}") from None
    else:
        clash = sorted(set(pose.joint_names) & set(data.labels))
        if clash:
            raise MocapflowError(f"joint names {', '.join(clash)} are also marker labels in {args.input}")
        extra = {**data.extra, **{name: pose.joint_centres[:, j] for j, name in enumerate(pose.joint_names)}}
        write_markers(out, MarkerData(positions=data.positions, labels=data.labels, rate=data.rate,
                                      first_frame=data.first_frame, flags=data.flags, extra=extra))
    posed = np.isfinite(pose.rotations).all(-1)
    print(f"wrote {out}: {len(pose.joint_names)} joints over {data.n_frames} frames; segments posed in "
          f"{100 * posed.mean():.1f} % of frames, mean marker fit {pose.marker_fit:.2f} mm")
    if missing:
        print(f"markers of the skeleton absent from the file: {', '.join(missing)}")
    print(fit_warning(pose.segment_names, pose.residual, pose.marker_fit) or "", end="")
    return 0


FIT_WARN_MM = 10.0
"""Mean marker fit above which solve warns: the skeleton does not describe this recording well."""


def fit_warning(segments: list[str], residual: np.ndarray, fit: float) -> str | None:
    """A warning naming the segments responsible (by their (F, S) RMS residuals) when the mean marker fit is over
    FIT_WARN_MM."""
    if not fit > FIT_WARN_MM:
        return None
    seen = np.isfinite(residual)
    per = np.where(seen.any(0), np.where(seen, residual, 0.0).sum(0) / np.maximum(seen.sum(0), 1), np.nan)
    worst = [f"{segments[s]} ({per[s]:.1f} mm)" for s in np.argsort(-np.nan_to_num(per)) if per[s] > FIT_WARN_MM]
    return (f"warning: mean marker fit {fit:.1f} mm is over {FIT_WARN_MM:g} mm; worst fitted: "
            f"{', '.join(worst)}: calibrate from a trial with this subject's markers, or check their labels\n")
