"""Picture of the simulator's camera model: docs/img/simulator-cameras.png.

Run: python benchmarks/camera_figure.py [--cameras N]. One frame of the simulated human (CMU 131_01 motion when the
shared data folder is present) seen by a ring of cameras: on the left from above, the cameras, the body and the ray of
every marker seen by one camera only; on the right the body from that camera's side, its segments drawn as the
capsules that occlude the cameras, and every marker coloured by how it reaches the tracker (a point: two cameras or
more; a ray: one camera; missing: none).
"""

from __future__ import annotations

import argparse

import _common
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mocapflow.io.bvh import read_bvh  # noqa: E402
from mocapflow.mocap.simulator import SimFrame, Simulator, SimulatorConfig  # noqa: E402

BVH = _common.DATA / "cmu_131_01.bvh"
OUT = _common.ROOT / "docs" / "img" / "simulator-cameras.png"
KINDS = (("point (2+ cameras)", "tab:green"), ("ray (1 camera)", "tab:orange"), ("missing (no camera)", "tab:red"))


def busiest_frame(sim: Simulator, frames: range) -> SimFrame:
    """The frame with the most single-camera markers, some unseen ones breaking ties."""
    best, score = sim.frame(frames[0]), -1.0
    for i in frames:
        f = sim.frame(i)
        assert f.rays is not None
        rays = np.isfinite(f.rays).all(axis=1)
        value = rays.sum() + 0.5 * min((~rays & ~f.visible).sum(), 3)
        if value > score:
            best, score = f, value
    return best


def capsule(ax: plt.Axes, start: np.ndarray, end: np.ndarray, radius: float, mm_to_points: float) -> None:
    ax.plot([start[0], end[0]], [start[1], end[1]], color="0.8", lw=2 * radius * mm_to_points,
            solid_capstyle="round", zorder=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cameras", type=int, default=4)
    args = parser.parse_args()
    bvh = read_bvh(BVH) if BVH.is_file() else None
    config = SimulatorConfig(rig="human", rate=120, seed=1, cameras=args.cameras,
                             bvh=str(BVH) if bvh is not None else None)
    sim = Simulator(config, bvh)
    f = busiest_frame(sim, range(0, 1200, 5))
    assert f.rays is not None
    rays = np.isfinite(f.rays).all(axis=1)
    kind = np.where(f.visible, 0, np.where(rays, 1, 2))
    cams = sim.camera_centres
    rot, pos = sim.segment_poses(f.frame)
    ends = pos + np.einsum("sij,sj->si", rot, sim.capsule_ends)

    fig, (top, side) = plt.subplots(1, 2, figsize=(12, 6.2), gridspec_kw={"width_ratios": [1, 1]})
    centre = f.true_positions.mean(axis=0)
    for m in np.flatnonzero(rays):  # each ray from its camera to its marker
        top.plot([f.rays[m, 0], f.true_positions[m, 0]], [f.rays[m, 1], f.true_positions[m, 1]], color="tab:orange",
                 lw=0.8, alpha=0.7)
    top.scatter(cams[:, 0], cams[:, 1], marker="^", s=120, color="k", zorder=3, label="camera")
    for c, (x, y, _) in enumerate(cams):
        top.annotate(f"{c + 1}", (x, y), textcoords="offset points", xytext=(8, 6))
    for k, (label, colour) in enumerate(KINDS):
        pick = kind == k
        top.scatter(f.true_positions[pick, 0], f.true_positions[pick, 1], s=10, color=colour, zorder=4, label=label)
    top.set_aspect("equal")
    top.set_title(f"from above: {args.cameras} cameras, frame {f.frame}", fontsize=10)
    top.set_xlabel("x (mm)")
    top.set_ylabel("y (mm)")
    top.legend(loc="lower left", fontsize=8)
    top.grid(alpha=0.3)

    # the body seen from the side of the camera that sees the most single-camera markers, projected on the plane
    # through the body's centre facing that camera
    seer = int(np.bincount(np.argmin(np.linalg.norm(f.rays[rays, None, :3] - cams[None], axis=2), axis=1),
                           minlength=len(cams)).argmax()) if rays.any() else 0
    view = cams[seer] - centre
    view[2] = 0.0
    view /= np.linalg.norm(view)
    right = np.cross([0.0, 0.0, 1.0], view)

    def project(p: np.ndarray) -> np.ndarray:
        rel = p - centre
        return np.stack([rel @ right, rel[..., 2] + centre[2]], axis=-1)

    extent = project(np.concatenate([pos, ends, f.true_positions]))
    low, high = extent.min(axis=0) - 150, extent.max(axis=0) + 150
    side.set_xlim(low[0], high[0])
    side.set_ylim(low[1], high[1])
    side.set_aspect("equal")
    near = (f.true_positions - centre) @ view
    for k, (label, colour) in enumerate(KINDS):
        pick = kind == k
        xy = project(f.true_positions[pick])
        side.scatter(xy[:, 0], xy[:, 1], s=np.where(near[pick] > 0, 28, 12), color=colour, edgecolor="k",
                     linewidths=0.4, zorder=3, label=label)
    side.set_title(f"facing camera {seer + 1}: segments as occluding capsules (large dots: near side)", fontsize=10)
    side.set_xlabel("across (mm)")
    side.set_ylabel("z (mm)")
    side.grid(alpha=0.3)
    counts = [int((kind == k).sum()) for k in range(3)]
    fig.suptitle(f"Simulated human, {len(kind)} markers: {counts[0]} points, {counts[1]} rays, {counts[2]} missing",
                 fontsize=11)
    fig.tight_layout()
    fig.canvas.draw()  # the capsules' widths in points follow the final size of the axes
    mm_to_points = side.get_window_extent().width * 72 / fig.dpi / (high[0] - low[0])
    for s in np.argsort(-(pos + ends) @ view):  # far capsules first
        capsule(side, project(pos[s]), project(ends[s]), sim.capsule_radii[s], mm_to_points)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(OUT, dpi=90)
    print(f"{OUT} ({OUT.stat().st_size // 1024} KB): frame {f.frame}, {counts[0]} points, {counts[1]} rays, "
          f"{counts[2]} missing")


if __name__ == "__main__":
    main()
