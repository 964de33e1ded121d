"""Occlusion filler: every marker in every frame, estimated where hidden (Aristidou 2008, ch. 5)."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from mocapflow.io.skeleton import read_skeleton
from mocapflow.messages import MarkerFrame, Skeleton
from mocapflow.mocap.compiled import compile_filling
from mocapflow.mocap.filling import FillerConfig, GapFiller
from mocapflow.mocap.flags import CASE_KALMAN, CASE_MISSING
from mocapflow.mocap.markerset import added
from mocapflow.mocap.model import SkeletonModel
from mocapflow.runtime.node import Input, Node, Output

ALONE = np.isin(np.arange(256), [CASE_MISSING, CASE_KALMAN])  # per flag: the marker has no estimate but its own filter


class FillerNodeConfig(FillerConfig):
    skeleton: str | None = Field(default=None, description="SKELETON.json to fill with from the first frame")


class Filler(Node[FillerNodeConfig]):
    """Kalman filter per marker fused with rigid-body constraints; causal. Flags say how each sample was obtained.
    Also publishes, after each frame, its prediction of the next one (the labeller re-identifies markers with it): of
    the markers seen, or placed by the body's constraints, in this one (a filter coasting alone is left out)."""

    Config = FillerNodeConfig
    inputs = {
        "markers": Input(MarkerFrame, doc="labelled markers with gaps"),
        "skeleton": Input(Skeleton, required=False, state=True, doc="body model; unlinked, one is learned online"),
    }
    outputs = {
        "markers": Output(MarkerFrame, doc="filled markers with per-sample flags"),
        "predictions": Output(MarkerFrame, doc="predicted positions for the next frame of the markers seen or placed "
                                               "by the body's constraints in this one (NaN for the others)"),
    }
    kernels = (compile_filling,)

    def setup(self) -> None:
        self.model: SkeletonModel | None = read_skeleton(self.config.skeleton) if self.config.skeleton else None
        self.filler: GapFiller | None = None

    def _filling(self) -> FillerConfig:
        """The filler's settings: a graph that links a skeleton input has one skeleton learner, the stage that feeds
        it, so the filler learns none of its own (it fills by its Kalman filters alone until the model comes)."""
        if self.linked is not None and "skeleton" in self.linked:
            return self.config.model_copy(update={"learn": False})
        return self.config

    def process(self, port: str, message: MarkerFrame | Skeleton) -> None:
        if isinstance(message, Skeleton):
            self.model = message.skeleton
            if self.filler is not None:
                self.filler.set_skeleton(self.model)
            return
        if message.labels is None:
            raise ValueError("the filler needs labelled markers: link it after a labeller")
        if self.filler is None or self.filler.labels != message.labels:
            if self.filler is not None and added(self.filler.labels, message.labels):
                self.filler.grow(message.labels)  # new markers confirmed upstream: everything known is kept
            else:  # another marker set
                self.filler = GapFiller(message.labels, message.rate, self._filling(), self.model)
        result = self.filler.update(message.positions, message.rays)  # filled in float64, on a copy
        self.publish("markers", MarkerFrame.derive(message, positions=result.positions, labels=message.labels,
                                                   flags=result.flags))
        if not self.listened("predictions"):  # a graph whose markers come labelled: no labeller to tell
            return
        predicted = self.filler.predict_next()
        predicted[ALONE[result.flags]] = np.nan  # a filter coasting alone knows no more than the labeller's own coast
        self.publish("predictions", MarkerFrame.derive(message, frame=message.frame + 1, positions=predicted,
                                                       labels=message.labels))
