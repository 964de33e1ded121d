"""Skeleton labeller: names each point with the marker names of a calibrated skeleton, from the first frame on."""

from __future__ import annotations

from pydantic import Field

from mocapflow.io.skeleton import read_skeleton
from mocapflow.messages import MarkerFrame
from mocapflow.mocap.compiled import compile_fits, compile_model_labelling
from mocapflow.mocap.labelling.model import ModelLabellerConfig, TrackedModelLabeller
from mocapflow.runtime.node import Input, Node, Output


class SkeletonLabellerConfig(ModelLabellerConfig):
    skeleton: str = Field(description="SKELETON.json of the subject (mocapflow calibrate on a labelled trial)")


class SkeletonLabeller(Node[SkeletonLabellerConfig]):
    """Names the points of each frame with the skeleton's own marker names by fitting its segments' marker layouts,
    and keeps a name with its point's track where the layouts do not decide (``TrackedModelLabeller``): the lab's
    names from trial to trial, whatever the point order and however long a marker was hidden. It keeps no state worth
    saving: restarted, it finds the segments again by their layouts in the first frames it gets. Points that fit no
    marker (ghosts, markers the skeleton does not know) are left out."""

    Config = SkeletonLabellerConfig
    inputs = {"markers": Input(MarkerFrame, doc="raw points, unlabelled")}
    outputs = {"markers": Output(MarkerFrame, doc="the skeleton's markers, NaN where not found")}
    kernels = (compile_fits, compile_model_labelling)

    def setup(self) -> None:
        self.skeleton = read_skeleton(self.config.skeleton)
        self.tolerances = ModelLabellerConfig(**self.config.model_dump(exclude={"skeleton"}))
        try:  # a skeleton it cannot use fails the node now, not at the first frame
            TrackedModelLabeller(self.skeleton, 1.0, self.tolerances)
        except ValueError as exc:
            raise ValueError(f"{self.config.skeleton}: {exc}") from None
        self.labeller: TrackedModelLabeller | None = None
        self.late = 0  # frames that came no later than the last one labelled, and were left out

    def process(self, port: str, message: MarkerFrame) -> None:
        if self.labeller is None or self.labeller.rate != message.rate:
            self.labeller = TrackedModelLabeller(self.skeleton, message.rate, self.tolerances)
        time = message.frame / message.rate
        if time <= self.labeller.time:
            self.late += 1
            if self.late == 1:
                self.log.warning("frame %d came after a later one and was left out (counted from now on)",
                                 message.frame)
            return
        positions, _ = self.labeller.update(message.positions, time)
        self.publish("markers", MarkerFrame.derive(message, positions=positions, labels=self.labeller.labels))

    def finish(self) -> None:
        if self.late:
            self.log.warning("%d frames came after later ones and were left out", self.late)
