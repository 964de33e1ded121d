"""Labeller: one persistent identity per physical marker, from unlabelled point clouds (Schoenauer 2007, 3.3)."""

from __future__ import annotations

import numpy as np

from mocapflow.messages import MarkerFrame, Segments
from mocapflow.mocap.compiled import compile_labelling
from mocapflow.mocap.labelling import Labeller, LabellerConfig
from mocapflow.mocap.reacquire import Reacquirer
from mocapflow.runtime.node import Input, Node, Output
from mocapflow.runtime.resume import StateKeeper

SAVE_EVERY_S = 0.5
RESUME_S = 1.0  # after a restart, how long lost tracks are looked for by their layouts


class LabellerNode(Node[LabellerConfig]):
    """Tracks points frame to frame; re-identifies reappearing markers from their segment mates or, when linked, from
    the gap filler's predictions. Publishes the confirmed markers in a fixed order that only grows, with the
    single-camera rays it could attribute to markers it did not see.

    Twice a second of stream time it keeps its tracks (``mocapflow.runtime.resume``): restarted within the same run,
    it carries on with them and finds each marker again by its rigid layout (``mocapflow.mocap.reacquire``), so a label
    keeps naming the same marker. Frames with no point at all for longer than a coast (a blinded tracker) are
    followed the same way."""

    Config = LabellerConfig
    inputs = {
        "markers": Input(MarkerFrame, doc="raw points, unlabelled"),
        "predictions": Input(MarkerFrame, required=False, doc="predicted positions of the labelled markers"),
        "segments": Input(Segments, required=False, state=True, doc="which markers move together"),
    }
    outputs = {"markers": Output(MarkerFrame, doc="labelled markers, NaN where not seen")}
    kernels = (compile_labelling,)

    def setup(self) -> None:
        self.keeper = StateKeeper(self.run_id, self.name)
        self.labeller: Labeller | None = self.keeper.load()
        self._saved_at = -float("inf")
        self.reacquire = Reacquirer(self.labeller) if self.labeller is not None else None
        self._resumed_at: float | None = None  # stream time of the first frame after a restart
        self._empty_since: float | None = None  # stream time of the first of consecutive frames with no point
        if self.labeller is not None:
            self.log.info("resuming %d tracks after a restart", len(self.labeller.labels))
        self.predictions: MarkerFrame | None = None
        self._rows_for: tuple[list[str], int] | None = None  # prediction labels and track count self._rows serves
        # tracks, and their rows in the predictions; None where the rows are the first tracks, in order
        self._rows: tuple[np.ndarray, np.ndarray] | None = np.empty(0, np.intp), np.empty(0, np.intp)
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
        time = frame.frame / frame.rate
        if not np.isfinite(frame.positions).all(axis=1).any():  # nothing seen: every marker is being lost at once
            self._empty_since = time if self._empty_since is None else self._empty_since
        elif self._empty_since is not None:
            if time - self._empty_since > labeller.config.max_coast_s and self.reacquire is None:
                self.reacquire, self._resumed_at = Reacquirer(labeller), None  # as after a restart
            self._empty_since = None
        if self.reacquire is not None:  # every marker was lost while this node restarted: find them by their layouts
            self._resumed_at = time if self._resumed_at is None else self._resumed_at
            self.reacquire(frame.positions.astype(np.float64), time)
            found = len(self.reacquire.found)
            if time - self._resumed_at >= RESUME_S or found >= len(labeller.labels):
                self.log.info("found %d of %d tracks again by their rigid layouts", found, len(labeller.labels))
                self.reacquire = None
        result = labeller.update(frame.positions.astype(np.float64), frame.frame / frame.rate, self._predicted(frame),
                                 rays)
        self.publish("markers", MarkerFrame.derive(frame, positions=result.positions, labels=list(labeller.labels),
                                                   rays=result.rays))
        if len(labeller.labels) != before:
            self._apply_segments()
        if frame.frame / frame.rate - self._saved_at >= SAVE_EVERY_S:
            self.keeper.save(labeller)
            self._saved_at = frame.frame / frame.rate

    def finish(self) -> None:
        self.keeper.clear()

    def _predicted(self, frame: MarkerFrame) -> np.ndarray | None:
        """The filler's predictions for this very frame, in track order; None when there are none for it.

        Which prediction row serves which track is kept while both label lists stay the same (they only grow)."""
        p = self.predictions
        if p is None or p.frame != frame.frame or p.labels is None or self.labeller is None:
            return None
        labels = self.labeller.labels
        if self._rows_for != (p.labels, len(labels)):
            index = {label: i for i, label in enumerate(p.labels)}
            tracks = [t for t, label in enumerate(labels) if label in index]
            rows = np.array(tracks, np.intp), np.array([index[labels[t]] for t in tracks], np.intp)
            same = len(tracks) == len(p.labels) and all(np.array_equal(r, np.arange(len(r))) for r in rows)
            self._rows = None if same else rows
            self._rows_for = (list(p.labels), len(labels))
        out = np.empty((len(labels), 3))
        out.fill(np.nan)
        if self._rows is None:  # the same markers in the same order, the newest tracks perhaps not yet filled
            out[:len(p.positions)] = p.positions
        else:
            out[self._rows[0]] = p.positions[self._rows[1]]
        return out

    def _apply_segments(self) -> None:
        if self.segments is None or self.labeller is None:
            return
        index = {label: i for i, label in enumerate(self.labeller.labels)}
        groups = [[index[m] for m in seg.markers if m in index] for seg in self.segments.segments]
        self.labeller.set_segments([g for g in groups if len(g) > 1])
