"""Skeleton publisher: per-frame segment rotations and joint centres of the parameterised skeleton."""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mocapflow.io.skeleton import read_skeleton
from mocapflow.messages import MarkerFrame, Pose, Skeleton
from mocapflow.mocap.compiled import compile_fits
from mocapflow.mocap.model import SkeletonModel
from mocapflow.mocap.solve import PoseSolver
from mocapflow.runtime.node import Input, Node, Output


class SkeletonConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    skeleton: str | None = Field(default=None, description="SKELETON.json to use until a model arrives")


class SkeletonPublisher(Node[SkeletonConfig]):
    """Fits the rigid skeleton to each frame, root first (Schoenauer 2007, 3.8.2). Fed with filled markers, joint
    centres stay available through occlusions."""

    Config = SkeletonConfig
    inputs = {
        "markers": Input(MarkerFrame, doc="labelled, preferably filled, markers"),
        "skeleton": Input(Skeleton, required=False, state=True, doc="the skeleton model to fit"),
    }
    outputs = {"pose": Output(Pose, doc="joint centres and segment rotations")}
    kernels = (compile_fits,)

    def setup(self) -> None:
        self.model: SkeletonModel | None = read_skeleton(self.config.skeleton) if self.config.skeleton else None
        self.solver: PoseSolver | None = None  # compiled for self.model and the labels last seen; None when stale
        self.frames = self.posed = 0

    def process(self, port: str, message: MarkerFrame | Skeleton) -> None:
        self.process_batch(port, [message])

    def process_batch(self, port: str, messages: list[MarkerFrame | Skeleton]) -> None:
        """Frames that queued up are solved together: the solver is vectorised over frames. It is compiled once for
        the model and the frames' labels and kept until either changes."""
        if port == "skeleton":
            last = messages[-1]
            assert isinstance(last, Skeleton)
            self.model, self.solver = last.skeleton, None
            return
        self._solve([m for m in messages if isinstance(m, MarkerFrame)])

    def _solve(self, frames: list[MarkerFrame]) -> None:
        labels = frames[0].labels
        if self.model is None or labels is None:
            self.frames += len(frames)
            return
        if any(m.labels != labels for m in frames):  # the marker set changed inside the batch: split it
            cut = next(i for i, m in enumerate(frames) if m.labels != labels)
            self._solve(frames[:cut])
            self._solve(frames[cut:])
            return
        if self.solver is None or self.solver.labels != labels:
            self.solver = PoseSolver(self.model, labels)
        pose = self.solver(np.array([m.positions for m in frames], dtype=np.float64))
        self.frames += len(frames)
        self.posed += len(frames)
        for i, m in enumerate(frames):
            self.publish("pose", Pose.derive(m, joint_names=pose.joint_names, joint_centres=pose.joint_centres[i],
                                             segment_names=pose.segment_names, rotations=pose.rotations[i],
                                             translations=pose.translations[i]))

    def finish(self) -> None:
        """A run that never posed a frame it received has no skeleton output at all: that is a failure to report,
        not a finished node."""
        if self.frames and not self.posed:
            raise RuntimeError(f"no skeleton in {self.frames} frames: no skeleton model arrived"
                               f"{'' if self.model is None else ' that fits these labels'}, no pose published"
                               " (a live joint estimator needs its warmup_s of motion first; a shorter stream needs a"
                               " calibrated skeleton, in this node's config 'skeleton')")
