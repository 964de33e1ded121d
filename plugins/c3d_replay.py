"""File tracker: replays a C3D or TRC recording in real time, as a tracker would stream it.

The file goes through ``read_markers``, the reader of the offline commands, so both see the same numbers: positions
in mm whatever the file's unit, zeros and invalid residuals as missing, ``Subject:`` label prefixes dropped when
unambiguous, labels past 255 (POINT:LABELS2...) kept, analog channels and model outputs skipped. A file that cannot
be read (not C3D/TRC, truncated, no points) stops the node at start with a one-line reason naming the file.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from mocapflow.io.markers import read_markers
from mocapflow.messages import MarkerFrame
from mocapflow.runtime.node import Node, Output


class ReplayConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    path: str = Field(description="C3D or TRC file to replay")
    speed: float = Field(default=1.0, gt=0, le=100, description="time factor: 2 replays twice as fast")
    loop: bool = Field(default=False, description="start again at the end instead of ending the stream")
    start: int = Field(default=0, ge=0, description="first frame to replay, counted from the file's first (0)")
    end: int | None = Field(default=None, ge=1, description="replay up to this frame, exclusive, counted like start "
                            "(none = to the end)")
    unlabelled: bool = Field(default=False, description="strip labels and shuffle points, like a passive tracker")
    seed: int = Field(default=0, description="shuffle seed in unlabelled mode")

    @model_validator(mode="after")
    def _range(self) -> ReplayConfig:
        if self.end is not None and self.end <= self.start:
            raise ValueError(f"end ({self.end}) must be after start ({self.start})")
        return self


class FileReplay(Node[ReplayConfig]):
    """Streams a marker file at its own rate (times ``speed``). Frame numbers are the file's own (its first frame
    number plus the row), so a recording of the stream is numbered like the file; when looping they keep rising, so
    downstream stages see one continuous capture. The stream ends after the last frame unless looping."""

    Config = ReplayConfig
    outputs = {"markers": Output(MarkerFrame, doc="the file's markers, labelled or as an unlabelled point cloud")}

    def setup(self) -> None:
        data = read_markers(self.config.path)
        end = min(self.config.end or len(data.positions), len(data.positions))
        if self.config.start >= end:
            raise ValueError(f"{self.config.path}: start frame {self.config.start} is past the last frame ({end - 1})")
        self.positions = data.positions[self.config.start:end]
        if not np.isfinite(self.positions).all(axis=2).any():
            raise ValueError(f"{self.config.path}: no marker position in frames {self.config.start} to {end - 1}")
        self.first_frame = data.first_frame + self.config.start
        self.labels = data.labels
        self.file_rate = data.rate
        self.rate = data.rate * self.config.speed
        self.log.info("replaying %s: %d frames x %d markers at %g Hz", self.config.path, len(self.positions),
                      len(self.labels), self.rate)

    def emit(self, index: int) -> bool:
        if index >= len(self.positions) and not self.config.loop:
            return False
        points = self.positions[index % len(self.positions)]
        labels: list[str] | None = self.labels
        if self.config.unlabelled:
            points = points[~np.isnan(points).any(axis=1)]
            points = points[np.random.default_rng([self.config.seed, index]).permutation(len(points))]
            labels = None
        self.publish("markers", MarkerFrame(frame=self.first_frame + index, capture_ns=self.due_ns(index),
                                            rate=self.file_rate, positions=points, labels=labels))
        return True
