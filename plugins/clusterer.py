"""Limb clusterers: which markers form rigid segments, from the spread of their mutual distances."""

from __future__ import annotations

from typing import Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field

from mocapflow.io.skeleton import read_skeleton
from mocapflow.messages import MarkerFrame, Segments
from mocapflow.mocap.clustering import SegmentTracker
from mocapflow.mocap.markerset import added
from mocapflow.runtime.node import Input, Node, Output
from mocapflow.runtime.sampling import Sampler


class ClustererConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    window_s: float = Field(default=20.0, gt=0, description="recent motion the distance statistics cover (s)")
    warmup_s: float = Field(default=5.0, gt=0, description="motion seen before the first partition (s)")
    sample_hz: float = Field(default=60.0, gt=0, description="rate at which frames enter the statistics (Hz); every "
                             "frame of a slower stream, at most the sampled copy's (about 120 Hz) unless the input "
                             "takes the whole stream ('queue: all')")
    every_s: float = Field(default=0.5, gt=0, description="how often the partition is computed again (s); up to four "
                           "times less often while it holds")
    segments: int | None = Field(default=None, ge=2, description="number of segments; none: chosen from the data")
    skeleton: str | None = Field(default=None, description="SKELETON.json whose segments are published at once")


class DistanceClustererConfig(ClustererConfig):
    threshold_mm: float = Field(default=5.0, gt=0, description="largest distance spread within a segment (mm)")


class RigidityClusterer(Node[ClustererConfig]):
    """Segments as the markers that keep their distances within the recording's own noise, as ``mocapflow
    calibrate`` finds them (``clustering.partition_rigidity``). Publishes a segment model after the warm-up and again
    only when it changes (at once, when seeded with a saved skeleton).

    The statistics sample the stream at ``sample_hz`` (by frame number, ``mocapflow.runtime.sampling``: from another
    process the node receives only the stream's sampled copy) and cover a long window, as the filler's learner does:
    a joint held still for a few seconds keeps the segments it was seen to separate, and each frame costs little."""

    Config: ClassVar[type[ClustererConfig]] = ClustererConfig
    method: ClassVar[Literal["rigidity", "spectral", "distance-threshold"]] = "rigidity"
    inputs = {"markers": Input(MarkerFrame, doc="labelled markers (filled ones too: only observed samples count)",
                               queue="sampled")}
    outputs = {"segments": Output(Segments, state=True, doc="the current segment model")}

    def setup(self) -> None:
        self.tracker: SegmentTracker | None = None
        self.sampler = Sampler(self.config.sample_hz)
        self.seed = read_skeleton(self.config.skeleton).segments if self.config.skeleton else None

    def options(self) -> dict[str, Any]:
        return {"k": self.config.segments}

    def process(self, port: str, message: MarkerFrame) -> None:
        if message.labels is None:
            raise ValueError("the clusterer needs labelled markers: link it after a labeller")
        if self.seed is not None:  # a calibrated subject: its segments from the first frame, no warm-up
            self.publish("segments", Segments.derive(message, segments=self.seed))
            self.seed = None
        if not self.sampler.take(message.frame, message.rate):
            return
        if self.tracker is not None and added(self.tracker.labels, message.labels):
            self.tracker.grow(message.labels)  # new markers confirmed upstream: the statistics so far still count
        elif self.tracker is None or self.tracker.labels != message.labels:  # another marker set
            config = self.config
            samples = self.sampler.rate(message.rate)
            self.tracker = SegmentTracker(message.labels, window=max(2, round(config.window_s * samples)),
                                          warmup=max(2, round(min(config.warmup_s, config.window_s) * samples)),
                                          every=max(1, round(config.every_s * samples)),
                                          method=self.method, **self.options())
        model = self.tracker.update(message.observed())
        if model is not None:
            self.log.info("segments: %s", "; ".join(f"{s.name}: {' '.join(s.markers)}" for s in model.segments))
            self.publish("segments", Segments.derive(message, segments=model.segments))


class SpectralClusterer(RigidityClusterer):
    """Spectral clustering of the distance-spread graph with local scaling (Schoenauer 2007, 3.4); the number of
    segments, unless given, from the eigengap."""

    method = "spectral"


class DistanceClusterer(RigidityClusterer):
    """Markers whose mutual distances vary less than a threshold form a segment (Aristidou 2008, 3.2)."""

    Config = DistanceClustererConfig
    method = "distance-threshold"

    def options(self) -> dict[str, Any]:
        config = self.config
        assert isinstance(config, DistanceClustererConfig)
        return {"k": config.segments, "threshold_mm": config.threshold_mm}
