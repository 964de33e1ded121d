"""Occlusion filler: every marker in every frame, estimated where hidden (Aristidou 2008, ch. 5)."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from mocapflow.io.skeleton import read_skeleton
from mocapflow.messages import MarkerFrame, Skeleton
from mocapflow.mocap.filling import FillerConfig, GapFiller
from mocapflow.mocap.model import SkeletonModel
from mocapflow.runtime.node import Input, Node, Output, Publish


class FillerNodeConfig(FillerConfig):
    skeleton: str | None = Field(default=None, description="SKELETON.json to fill with from the first frame")


class Filler(Node):
    """Kalman filter per marker fused with rigid-body constraints; causal. Flags say how each sample was obtained.
    Also publishes, after each frame, its prediction of the next one (the labeller re-identifies markers with it)."""

    Config = FillerNodeConfig
    inputs = {
        "markers": Input(MarkerFrame, doc="labelled markers with gaps"),
        "skeleton": Input(Skeleton, required=False, state=True, doc="body model; without one it is learned online"),
    }
    outputs = {
        "markers": Output(MarkerFrame, doc="filled markers with per-sample flags"),
        "predictions": Output(MarkerFrame, doc="predicted positions for the next frame"),
    }

    def __init__(self, config: FillerNodeConfig, publish: Publish, name: str = "filler") -> None:
        super().__init__(config, publish, name)
        self.filler_config = FillerConfig.model_validate(config.model_dump(exclude={"skeleton"}))
        self.model: SkeletonModel | None = read_skeleton(config.skeleton) if config.skeleton else None
        self.filler: GapFiller | None = None

    def process(self, port: str, message: MarkerFrame | Skeleton) -> None:
        if isinstance(message, Skeleton):
            self.model = message.skeleton
            if self.filler is not None:
                self.filler.set_skeleton(self.model)
            return
        if message.labels is None:
            raise ValueError("the filler needs labelled markers: link it after a labeller")
        if self.filler is None or self.filler.labels != message.labels:
            # new markers confirmed upstream: a filler for the new marker set
            self.filler = GapFiller(message.labels, message.rate, self.filler_config, self.model)
        result = self.filler.update(message.positions.astype(np.float64), message.rays)
        self.publish("markers", MarkerFrame(frame=message.frame, capture_ns=message.capture_ns, rate=message.rate,
                                            positions=result.positions, labels=message.labels, flags=result.flags))
        self.publish("predictions", MarkerFrame(frame=message.frame + 1, capture_ns=message.capture_ns,
                                                rate=message.rate, positions=self.filler.predict_next(),
                                                labels=message.labels))
