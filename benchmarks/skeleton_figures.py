"""Pictures of inferred skeletons drawn over their markers: docs/img/skeleton-simulated-human.png,
docs/img/skeleton-lowerbody.png and docs/img/skeleton-real-full-body.png.

Run: python benchmarks/skeleton_figures.py. Each picture shows one frame from the front and from the side: markers
coloured by the segment they were clustered into, the calibrated skeleton solved on that frame (joint centres, bones
in the segment's colour, hinge axes as short black bars) and, as black crosses, the reference joint centres (the
simulator's truth; for the real file the knee and ankle marker midpoints and the Harrington hip centres).
"""

from __future__ import annotations

from pathlib import Path

import _common
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mocapflow.io.markers import read_markers  # noqa: E402
from mocapflow.mocap.calibration import calibrate  # noqa: E402
from mocapflow.mocap.model import SkeletonModel  # noqa: E402
from mocapflow.mocap.rigidfit import quaternion_matrices  # noqa: E402
from mocapflow.mocap.simulator import SimulatorConfig, simulate  # noqa: E402
from mocapflow.mocap.solve import SkeletonPose, solve  # noqa: E402

OUT = _common.ROOT / "docs" / "img"
AXIS_MM = 60.0  # half length of a drawn hinge axis


def bones(skeleton: SkeletonModel, pose: SkeletonPose, f: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(segment, start, end) of every bone in frame ``f``: from a segment's joint with its parent to each of its
    other joints; the root from its marker centroid to its joints, an end segment from its joint to that centroid."""
    names = [s.name for s in skeleton.segments]
    centre = {j.name: pose.joint_centres[f, k] for k, j in enumerate(skeleton.joints)}
    out = []
    for s, segment in enumerate(skeleton.segments):
        up = [j.name for j in skeleton.joints if j.child == segment.name]
        down = [j.name for j in skeleton.joints if j.parent == segment.name]
        start = centre[up[0]] if up else pose.translations[f, s]
        ends = [centre[d] for d in down] or [pose.translations[f, s]]
        out += [(names.index(segment.name), start, end) for end in ends]
    return out


def draw(path: Path, title: str, skeleton: SkeletonModel, positions: np.ndarray, labels: list[str], f: int,
         references: np.ndarray, reference_label: str) -> None:
    """Front and side (from the right) views of frame ``f``, oriented by the pelvis markers; z is up."""
    pose = solve(skeleton, positions[f:f + 1], labels)
    frame = positions[f]
    index = {m: k for k, m in enumerate(labels)}
    left = frame[index["LASI"]] - frame[index["RASI"]]
    ahead = frame[[index["LASI"], index["RASI"]]].mean(0) - frame[[index["LPSI"], index["RPSI"]]].mean(0)
    left = np.array([left[0], left[1], 0.0]) / np.linalg.norm(left[:2])
    ahead = ahead - (ahead @ left) * left
    ahead = np.array([ahead[0], ahead[1], 0.0]) / np.linalg.norm(ahead[:2])
    views = [("front", left), ("side, from the right", ahead)]
    small = len(skeleton.segments) <= 9
    greys = (7,) if small else (14, 15)  # grey stays for the legend
    palette = [c for k, c in enumerate(plt.get_cmap("tab10" if small else "tab20").colors) if k not in greys]
    colours = palette[: len(skeleton.segments)]
    fig, axes = plt.subplots(1, 2, figsize=(10, 6.4), dpi=100, sharey=True)
    for ax, (view, horizontal) in zip(axes, views, strict=True):
        for s, segment in enumerate(skeleton.segments):
            pts = np.array([frame[index[m]] for m in segment.markers if np.isfinite(frame[index[m]]).all()])
            if len(pts):
                ax.scatter(pts @ horizontal, pts[:, 2], s=28, color=colours[s], edgecolor="none", zorder=2)
        for s, start, end in bones(skeleton, pose, 0):
            ax.plot([start @ horizontal, end @ horizontal], [start[2], end[2]], color=colours[s], lw=4,
                    solid_capstyle="round", zorder=3, alpha=0.85)
        for k, joint in enumerate(skeleton.joints):
            c = pose.joint_centres[0, k]
            if joint.kind == "hinge":
                parent = [x.name for x in skeleton.segments].index(joint.parent)
                axis = quaternion_matrices(pose.rotations[0, parent]) @ np.asarray(joint.axis)
                a, b = c - AXIS_MM * axis, c + AXIS_MM * axis
                ax.plot([a @ horizontal, b @ horizontal], [a[2], b[2]], color="black", lw=1.6, zorder=4)
            ax.scatter(c @ horizontal, c[2], s=46, color="white", edgecolor="black", linewidth=1.4, zorder=5)
        ok = np.isfinite(references).all(1)
        ax.scatter(references[ok] @ horizontal, references[ok, 2], marker="x", s=40, color="black", linewidth=1.2,
                   zorder=6)
        ax.set_title(view, fontsize=13)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("mm", fontsize=11)
        ax.tick_params(labelsize=10)
        ax.grid(alpha=0.25)
    axes[0].set_ylabel("height, mm", fontsize=11)
    handles = [plt.Line2D([], [], ls="", marker="o", ms=5, color="grey", label="markers (colour: segment)"),
               plt.Line2D([], [], lw=4, color="grey", label="bones (colour: segment)"),
               plt.Line2D([], [], ls="", marker="o", ms=7, mfc="white", mec="black", label="joint centres"),
               plt.Line2D([], [], lw=1.6, color="black", label="hinge axes"),
               plt.Line2D([], [], ls="", marker="x", ms=7, color="black", label=reference_label)]
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=11, frameon=False)
    fig.suptitle(title, fontsize=14)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    print(f"wrote {path} ({path.stat().st_size // 1024} KB)")


def simulated_human() -> None:
    """The simulated human in its most upright frame, with the simulator's true joint centres."""
    rec = simulate(SimulatorConfig(rig="human", rate=120, noise_mm=0.5, seed=0), 2000)
    skeleton = calibrate(rec.positions, rec.labels, rec.rate)
    height = np.nanmax(rec.positions[..., 2], 1) - np.nanmin(rec.positions[..., 2], 1)
    f = int(np.argmax(height))  # the most upright pose
    draw(OUT / "skeleton-simulated-human.png", "Simulated human: 52 markers, 15 segments and 14 joints found",
         skeleton, rec.positions, rec.labels, f, rec.joint_centres[f], "true joint centres")


def lower_body() -> None:
    """The real lower-body file in the frame where a knee is bent most, with the clinical landmarks."""
    path = _common.DATA / "lowerbody_clusters_knee_0401.c3d"
    if not path.is_file():
        print(f"{path} is absent: no real-data picture")
        return
    data = read_markers(path)
    positions = data.positions.astype(float)
    positions[(positions == 0).all(-1)] = np.nan
    skeleton = calibrate(positions, data.labels, data.rate)

    def at(label: str) -> np.ndarray:
        return positions[:, data.labels.index(label)]

    def bend(side: str) -> np.ndarray:
        thigh, shank = at(f"{side}LKN") - at(f"{side}ASI"), at(f"{side}LAK") - at(f"{side}LKN")
        return np.einsum("fa,fa->f", thigh, shank) / np.linalg.norm(thigh, axis=1) / np.linalg.norm(shank, axis=1)

    complete = np.isfinite(positions).all((1, 2))
    f = int(np.nanargmin(np.where(complete, np.minimum(bend("L"), bend("R")), np.nan)))  # a knee bent most
    from skeleton_accuracy import LowerBody  # the clinical landmarks of the accuracy table

    landmarks = LowerBody(data).landmarks()
    references = np.array([landmarks[k][f] for k in landmarks])
    draw(OUT / "skeleton-lowerbody.png", f"Real lower body ({path.name}): 8 segments and 7 joints found", skeleton,
         positions, data.labels, f, references, "clinical centres: marker midpoints, Harrington hips")


FULL_BODY = ("cmu_85_02.c3d", "cmu_85_12_breakdance.c3d", "cmu_02_05.c3d", "cmu_dribble_shoot_basketball.c3d",
             "hamner_run200.trc", "sprinter_JA1Gait35.c3d")


def real_full_body() -> None:
    """Every real full-body file calibrated with no option, one panel each from the front, in its most upright
    frame: markers coloured by segment, bones, joint centres."""
    files = [_common.DATA / name for name in FULL_BODY if (_common.DATA / name).is_file()]
    if not files:
        print(f"{_common.DATA} holds no full-body file: no picture")
        return
    fig, axes = plt.subplots(2, 3, figsize=(13, 10), dpi=90)
    for ax, path in zip(axes.ravel(), files, strict=False):
        data = read_markers(path)
        skeleton = calibrate(data.positions, data.labels, data.rate)
        extent = np.nanmax(data.positions, 1) - np.nanmin(data.positions, 1)  # (F, 3)
        up = int(np.argmax(np.nanmedian(extent, 0)))  # z in the C3D files, y in the TRC
        f = int(np.nanargmax(np.where(np.isfinite(data.positions).all((1, 2)), extent[:, up], np.nan)))
        pose = solve(skeleton, data.positions[f:f + 1], data.labels)
        frame = data.positions[f]
        short = [label.rpartition(":")[2] for label in data.labels]
        side = [k for k, n in enumerate(short) if n[:1] == "L"], [k for k, n in enumerate(short) if n[:1] == "R"]
        left = np.nanmean(frame[side[0]], 0) - np.nanmean(frame[side[1]], 0)
        left[up] = 0.0
        left /= np.linalg.norm(left)
        index = {m: k for k, m in enumerate(data.labels)}
        palette = plt.get_cmap("tab20").colors
        for s, segment in enumerate(skeleton.segments):
            pts = np.array([frame[index[m]] for m in segment.markers])
            ax.scatter(pts @ left, pts[:, up], s=22, color=palette[s % 20], edgecolor="none", zorder=2)
        for s, start, end in bones(skeleton, pose, 0):
            ax.plot([start @ left, end @ left], [start[up], end[up]], color=palette[s % 20], lw=3.5,
                    solid_capstyle="round", zorder=3, alpha=0.85)
        centres = pose.joint_centres[0]
        ax.scatter(centres @ left, centres[:, up], s=30, color="white", edgecolor="black", linewidth=1.1, zorder=5)
        ax.set_title(f"{path.name}\n{len(skeleton.segments)} segments, {len(skeleton.joints)} joints", fontsize=11)
        ax.set_aspect("equal", adjustable="datalim")
        ax.tick_params(labelsize=8)
        ax.grid(alpha=0.25)
    for ax in axes.ravel()[len(files):]:
        ax.axis("off")
    fig.suptitle("Real full-body recordings, calibrated with no option (front views; colour: segment; circles: "
                 "joint centres)", fontsize=12)
    fig.tight_layout()
    out = OUT / "skeleton-real-full-body.png"
    fig.savefig(out)
    plt.close(fig)
    print(f"wrote {out} ({out.stat().st_size // 1024} KB)")


if __name__ == "__main__":
    simulated_human()
    lower_body()
    real_full_body()
