"""Joint estimators: centres of rotation between segments, topology and rigid parameters -> the skeleton model."""

from __future__ import annotations

from collections import deque
from typing import ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mocapflow.errors import CalibrationError
from mocapflow.io.skeleton import read_skeleton
from mocapflow.messages import MarkerFrame, Segments, Skeleton
from mocapflow.mocap.calibration import build_skeleton
from mocapflow.mocap.compiled import compile_fits
from mocapflow.mocap.markerset import added
from mocapflow.runtime.node import Input, Node, Output
from mocapflow.runtime.sampling import Sampler


class JointsConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    skeleton: str | None = Field(default=None, description="SKELETON.json to publish at once (no warm-up)")
    refine: bool = Field(default=True, description="estimate the skeleton again from live data")
    window_s: float = Field(default=20.0, gt=0, description="recent motion the estimate uses (s)")
    warmup_s: float = Field(default=5.0, gt=0, description="motion seen before the first estimate (s), at most half "
                            "the window; later ones use all the window holds")
    every_s: float = Field(default=5.0, gt=0, description="time between two estimates (s)")
    sample_hz: float = Field(default=60.0, gt=0, description="rate at which frames enter the window (Hz); every "
                             "frame of a slower stream, at most the sampled copy's (about 120 Hz) unless the input "
                             "takes the whole stream ('queue: all')")


class VarianceJoints(Node[JointsConfig]):
    """Joint positions minimising the variance of marker-to-joint distances (Schoenauer 2007, 3.5), topology by
    minimum spanning tree, rigid parameters by Horn's method; recomputed over a sliding window of recent frames,
    sampled at ``sample_hz`` (the estimate samples its frames more sparsely still)."""

    Config = JointsConfig
    joint_method: ClassVar[Literal["variance", "closed-form", "auto"]] = "variance"
    inputs = {
        "markers": Input(MarkerFrame, doc="labelled markers (filled ones too: only observed samples count)",
                         queue="sampled"),
        "segments": Input(Segments, required=False, state=True, doc="segment model; without it no estimate is made"),
    }
    outputs = {"skeleton": Output(Skeleton, state=True, doc="the current skeleton model")}
    kernels = (compile_fits,)

    def setup(self) -> None:
        self.seed = read_skeleton(self.config.skeleton) if self.config.skeleton else None
        self.published = False
        self.segments: Segments | None = None
        self.frames: deque[np.ndarray] = deque()
        self.labels: list[str] | None = None
        self.next_estimate = 0  # samples to the next estimate
        self.sampler = Sampler(self.config.sample_hz)

    def wanted(self, port: str) -> bool:
        """With ``refine`` off, only the first frame (which publishes the given skeleton): the others are passed over
        undecoded."""
        return self.config.refine or not self.published

    def process(self, port: str, message: MarkerFrame | Segments) -> None:
        if isinstance(message, Segments):
            self.segments = message
            return
        if self.seed is not None and not self.published:
            self.published = True
            self.publish("skeleton", Skeleton.derive(message, skeleton=self.seed))
        if not self.config.refine or message.labels is None or not self.sampler.take(message.frame, message.rate):
            return
        if message.labels != self.labels:
            new = added(self.labels or [], message.labels)
            if new is not None:  # new markers confirmed upstream: the frames so far still count
                pad = np.full((len(new), 3), np.nan)
                self.frames = deque(np.vstack([f, pad]) for f in self.frames)
            else:
                self.frames.clear()
                self.next_estimate = 0
            self.labels = message.labels
        samples = self.sampler.rate(message.rate)
        self.frames.append(message.observed())
        window = round(self.config.window_s * samples)
        while len(self.frames) > window:
            self.frames.popleft()
        self.next_estimate -= 1
        warmup = min(round(self.config.warmup_s * samples), window // 2)
        if self.segments is None or self.next_estimate > 0 or len(self.frames) < warmup:
            return
        self.next_estimate = round(self.config.every_s * samples)
        index = {label: i for i, label in enumerate(self.labels)}
        groups = [[index[m] for m in s.markers if m in index] for s in self.segments.segments]
        try:
            skeleton = build_skeleton(np.stack(self.frames), self.labels, samples, [g for g in groups if g],
                                      self.joint_method)
        except CalibrationError as exc:
            self.log.warning("no skeleton yet: %s", exc)
            return
        self.published = True
        self.log.info("skeleton: root %s, joints %s", skeleton.root,
                      ", ".join(f"{j.parent}-{j.child}" for j in skeleton.joints))
        self.publish("skeleton", Skeleton.derive(message, skeleton=skeleton))


class ClosedFormJoints(VarianceJoints):
    """Centres of rotation by the closed-form least-squares solution of Aristidou 2008, 4.4 (6 x 6 system, Schur
    complement), topology by minimum spanning tree; recomputed over a sliding window of recent frames. A segment of
    two markers, whose orientation they cannot fix, is placed down the tree from its neighbours, as ``mocapflow
    calibrate`` does, rather than holding back the whole skeleton."""

    joint_method = "auto"
