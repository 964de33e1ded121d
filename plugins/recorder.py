"""Recorder sink: writes a marker stream (and solved joint centres, when linked) to a C3D or TRC file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from mocapflow.io.markers import MarkerData, write_markers
from mocapflow.messages import MarkerFrame, Pose
from mocapflow.runtime.node import Input, Node, Publish


class RecorderConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    path: str = Field(description="output file; .c3d or .trc")

    @field_validator("path")
    @classmethod
    def _suffix(cls, path: str) -> str:
        if Path(path).suffix.lower() not in (".c3d", ".trc"):
            raise ValueError(f"{path!r}: the recorder writes .c3d or .trc files")
        return path


class Recorder(Node):
    """Writes every received frame at its frame number; frames that never arrived are left missing (NaN). Joint
    centres become one extra point per joint name ever received (the skeleton may change during a run), missing in
    frames whose pose lacks that joint."""

    Config = RecorderConfig
    inputs = {
        "markers": Input(MarkerFrame, doc="markers to record"),
        "pose": Input(Pose, required=False, doc="solved poses: joint centres are written as extra points"),
    }

    def __init__(self, config: RecorderConfig, publish: Publish, name: str = "recorder") -> None:
        super().__init__(config, publish, name)
        self.frames: dict[int, np.ndarray] = {}
        self.flags: dict[int, np.ndarray] = {}
        self.joints: dict[str, dict[int, np.ndarray]] = {}  # joint name -> frame -> centre
        self.labels: list[str] | None = None
        self.rate = 0.0

    def process(self, port: str, message: MarkerFrame | Pose) -> None:
        if isinstance(message, Pose):
            for name, centre in zip(message.joint_names, message.joint_centres, strict=True):
                self.joints.setdefault(name, {})[message.frame] = centre
            return
        if self.labels is None and message.labels is not None:
            self.labels = message.labels
        self.rate = message.rate
        self.frames[message.frame] = message.positions
        if message.flags is not None:
            self.flags[message.frame] = message.flags

    def finish(self) -> None:
        if not self.frames:
            self.log.warning("no frame received: %s not written", self.config.path)
            return
        first, last = min(self.frames), max(self.frames)
        width = max(len(p) for p in self.frames.values())
        positions = np.full((last - first + 1, width, 3), np.nan)
        flags = np.zeros((last - first + 1, width), np.uint8) if self.flags else None
        for i, p in self.frames.items():
            positions[i - first, : len(p)] = p
            if flags is not None and i in self.flags:
                flags[i - first, : len(p)] = self.flags[i]
        labels = self.labels if self.labels and len(self.labels) == width else [f"P{i + 1:03d}" for i in range(width)]
        extra = {}
        for name, centres in self.joints.items():
            track = extra[name] = np.full((last - first + 1, 3), np.nan)
            for i, centre in centres.items():
                if first <= i <= last:
                    track[i - first] = centre
        path = Path(self.config.path)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_markers(path, MarkerData(positions=positions, labels=labels, rate=self.rate, first_frame=first,
                                       flags=flags, extra=extra))
        self.log.info("wrote %d frames x %d markers to %s", len(positions), width, path)
