"""Labeller: one persistent identity per physical marker, from unlabelled point clouds (Schoenauer 2007, 3.3)."""

from __future__ import annotations

import numpy as np

from mocapflow.messages import MarkerFrame, Segments
from mocapflow.mocap.labelling import Labeller, LabellerConfig
from mocapflow.runtime.node import Input, Node, Output


class LabellerNode(Node[LabellerConfig]):
    """Tracks points frame to frame; re-identifies reappearing markers from their segment mates or, when linked, from
    the gap filler's predictions. Publishes the confirmed markers in a fixed order that only grows, with the
    single-camera rays it could attribute to markers it did not see."""

    Config = LabellerConfig
    inputs = {
        "markers": Input(MarkerFrame, doc="raw points, unlabelled"),
        "predictions": Input(MarkerFrame, required=False, doc="predicted positions of the labelled markers"),
        "segments": Input(Segments, required=False, state=True, doc="which markers move together"),
    }
    outputs = {"markers": Output(MarkerFrame, doc="labelled markers, NaN where not seen")}

    def setup(self) -> None:
        self.labeller: Labeller | None = None
        self.predictions: MarkerFrame | None = None
        self.segments: Segments | None = None

    def process(self, port: str, message: MarkerFrame | Segments) -> None:
        if isinstance(message, Segments):
            self.segments = message
            self._apply_segments()
        elif port == "predictions":
            self.predictions = message
        else:
            self._label(message)

    def _label(self, frame: MarkerFrame) -> None:
        if self.labeller is None:
            self.labeller = Labeller(self.config, frame.rate)
        labeller = self.labeller
        before = len(labeller.labels)
        rays = None if frame.rays is None else frame.rays.astype(np.float64)
        result = labeller.update(frame.positions.astype(np.float64), frame.frame / frame.rate, self._predicted(frame),
                                 rays)
        self.publish("markers", MarkerFrame.derive(frame, positions=result.positions, labels=list(labeller.labels),
                                                   rays=result.rays))
        if len(labeller.labels) != before:
            self._apply_segments()

    def _predicted(self, frame: MarkerFrame) -> np.ndarray | None:
        """The filler's predictions for this very frame, in track order; None when there are none for it."""
        p = self.predictions
        if p is None or p.frame != frame.frame or p.labels is None or self.labeller is None:
            return None
        index = {label: i for i, label in enumerate(p.labels)}
        out = np.full((len(self.labeller.labels), 3), np.nan)
        for t, label in enumerate(self.labeller.labels):
            if label in index:
                out[t] = p.positions[index[label]]
        return out

    def _apply_segments(self) -> None:
        if self.segments is None or self.labeller is None:
            return
        index = {label: i for i, label in enumerate(self.labeller.labels)}
        groups = [[index[m] for m in seg.markers if m in index] for seg in self.segments.segments]
        self.labeller.set_segments([g for g in groups if len(g) > 1])
