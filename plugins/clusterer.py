"""Limb clusterers: which markers form rigid segments, from the spread of their mutual distances."""

from __future__ import annotations

from typing import Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field

from mocapflow.io.skeleton import read_skeleton
from mocapflow.messages import MarkerFrame, Segments
from mocapflow.mocap.clustering import SegmentTracker
from mocapflow.mocap.markerset import added
from mocapflow.runtime.node import Input, Node, Output


class ClustererConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    window_s: float = Field(default=5.0, gt=0, description="sliding window of distance statistics (s)")
    every_s: float = Field(default=0.5, gt=0, description="how often the partition is computed again (s); up to four "
                           "times less often while it holds")
    segments: int | None = Field(default=None, ge=2, description="number of segments; none: chosen from the data")
    skeleton: str | None = Field(default=None, description="SKELETON.json whose segments are published at once")


class DistanceClustererConfig(ClustererConfig):
    threshold_mm: float = Field(default=5.0, gt=0, description="largest distance spread within a segment (mm)")


class SpectralClusterer(Node[ClustererConfig]):
    """Spectral clustering of the distance-spread graph with local scaling (Schoenauer 2007, 3.4). Publishes a
    segment model after one window and again only when it changes (at once, when seeded with a saved skeleton)."""

    Config: ClassVar[type[ClustererConfig]] = ClustererConfig
    method: ClassVar[Literal["spectral", "distance-threshold"]] = "spectral"
    inputs = {"markers": Input(MarkerFrame, doc="labelled markers")}
    outputs = {"segments": Output(Segments, state=True, doc="the current segment model")}

    def setup(self) -> None:
        self.tracker: SegmentTracker | None = None
        self.seed = read_skeleton(self.config.skeleton).segments if self.config.skeleton else None

    def options(self) -> dict[str, Any]:
        return {"k": self.config.segments}

    def process(self, port: str, message: MarkerFrame) -> None:
        if message.labels is None:
            raise ValueError("the clusterer needs labelled markers: link it after a labeller")
        if self.seed is not None:  # a calibrated subject: its segments from the first frame, no warm-up
            self.publish("segments", Segments.derive(message, segments=self.seed))
            self.seed = None
        if self.tracker is not None and added(self.tracker.labels, message.labels):
            self.tracker.grow(message.labels)  # new markers confirmed upstream: the statistics so far still count
        elif self.tracker is None or self.tracker.labels != message.labels:  # another marker set
            window = max(2, round(self.config.window_s * message.rate))
            self.tracker = SegmentTracker(message.labels, window=window,
                                          every=max(1, round(self.config.every_s * message.rate)),
                                          method=self.method, **self.options())
        model = self.tracker.update(message.positions)
        if model is not None:
            self.log.info("segments: %s", "; ".join(f"{s.name}: {' '.join(s.markers)}" for s in model.segments))
            self.publish("segments", Segments.derive(message, segments=model.segments))


class DistanceClusterer(SpectralClusterer):
    """Markers whose mutual distances vary less than a threshold form a segment (Aristidou 2008, 3.2)."""

    Config = DistanceClustererConfig
    method = "distance-threshold"

    def options(self) -> dict[str, Any]:
        config = self.config
        assert isinstance(config, DistanceClustererConfig)
        return {"k": config.segments, "threshold_mm": config.threshold_mm}
