"""Viewer sink: draws markers, joint centres and bones, in a window or as PNG snapshots for a headless machine."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mocapflow.messages import MarkerFrame, Pose, Skeleton
from mocapflow.runtime.node import Input, Node


class ViewerConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    path: str | None = Field(default=None, description="write snapshots to this PNG instead of opening a window")
    fps: float = Field(default=15.0, gt=0, le=60, description="drawing rate; frames in between are skipped")
    size_mm: float = Field(default=2500.0, gt=0, description="side of the cube shown around the markers")


class Viewer(Node[ViewerConfig]):
    """Shows the latest frame at up to ``fps``, skipping frames so that drawing never holds the stream back."""

    Config = ViewerConfig
    inputs = {
        "markers": Input(MarkerFrame),
        "pose": Input(Pose, required=False, doc="joint centres to draw"),
        "skeleton": Input(Skeleton, required=False, state=True, doc="joint tree for the bones"),
    }

    def setup(self) -> None:
        try:
            import matplotlib
        except ImportError:
            raise RuntimeError("the viewer needs matplotlib: pip install 'mocapflow[viewer]'") from None
        if self.config.path or not os.environ.get("DISPLAY"):
            matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        self.plt = plt
        self.figure = plt.figure(figsize=(7, 7))
        self.axes = self.figure.add_subplot(projection="3d")
        self.interactive = matplotlib.get_backend().lower() != "agg"
        if self.interactive:
            plt.ion()
            plt.show(block=False)
        elif not self.config.path:
            self.log.warning("no display: nothing will be shown; set path to write PNG snapshots")
        self.markers: MarkerFrame | None = None
        self.pose: Pose | None = None
        self.bones: list[tuple[str, str]] = []
        self._next_draw = 0.0

    def process(self, port: str, message: MarkerFrame | Pose | Skeleton) -> None:
        if isinstance(message, Skeleton):
            # a bone joins a joint to the joint of its parent segment's own parent joint
            joint_of_child = {j.child: j.name for j in message.skeleton.joints}
            self.bones = [(joint_of_child[j.parent], j.name) for j in message.skeleton.joints
                          if j.parent in joint_of_child]
            return
        if isinstance(message, Pose):
            self.pose = message
            return
        self.markers = message
        now = time.monotonic()
        if now >= self._next_draw:
            self.draw()
            # Drawing shares the node's thread: keep it under a quarter of the time so frames never pile up.
            spent = time.monotonic() - now
            self._next_draw = now + max(1.0 / self.config.fps, 4 * spent)

    def draw(self) -> None:
        ax, frame = self.axes, self.markers
        if frame is None:
            return
        ax.cla()
        points = frame.positions[~np.isnan(frame.positions).any(axis=1)]
        centre = np.median(points, axis=0) if len(points) else np.zeros(3)
        half = self.config.size_mm / 2
        if frame.flags is not None:
            seen = frame.flags[~np.isnan(frame.positions).any(axis=1)] == 1
            ax.scatter(*points[seen].T, s=8, c="tab:blue", label="observed")
            ax.scatter(*points[~seen].T, s=14, c="tab:orange", label="estimated")
        else:
            ax.scatter(*points.T, s=8, c="tab:blue", label="markers")
        if self.pose is not None:
            centres = dict(zip(self.pose.joint_names, self.pose.joint_centres, strict=True))
            xyz = np.array(list(centres.values()))
            ax.scatter(*xyz.T, s=30, c="tab:red", marker="s", label="joints")
            for a, b in self.bones:
                if a in centres and b in centres:
                    ax.plot(*np.stack([centres[a], centres[b]]).T, c="tab:red", lw=2)
        for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, strict=True):
            setter(c - half, c + half)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_zlabel("z (mm)")
        ax.set_title(f"frame {frame.frame}: {len(points)} points")
        ax.legend(loc="upper left")
        if self.interactive:
            self.figure.canvas.draw_idle()
            self.figure.canvas.flush_events()
        elif self.config.path:
            Path(self.config.path).parent.mkdir(parents=True, exist_ok=True)
            tmp = Path(self.config.path).with_suffix(".tmp.png")
            self.figure.savefig(tmp, dpi=80)
            tmp.replace(self.config.path)  # readers never see a half-written picture

    def finish(self) -> None:
        self.plt.close(self.figure)
