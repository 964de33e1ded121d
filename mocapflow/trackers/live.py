"""What every live tracker adapter shares: mapping the tracker's clock to this machine's, keeping frame numbers
increasing across reconnections, and a source node fed by the vendor client's thread (docs/tracker-adapters.md)."""

from __future__ import annotations

import queue
import threading
import time
from collections import deque
from collections.abc import Sequence

import numpy as np

from mocapflow.io.markerdata import clean_labels
from mocapflow.messages import MarkerFrame
from mocapflow.runtime.node import ConfigT, Node, Output

RESUME_GAP_S = 1.0
"""A silence this long is a reconnection: the tracker may have restarted its frame count and its clock."""
WARN_SILENCE_S = 5.0
IDLE_WAIT_S = 0.1


class TrackerClock:
    """``capture_ns = tracker_ns + offset`` with ``offset = min(arrival_ns - tracker_ns)`` over the frames of the last
    ``window_s`` seconds: the least-delayed packet bounds the offset most tightly, and frame-to-frame timing stays the
    tracker's, free of network jitter. The window follows the drift between the two clocks."""

    def __init__(self, window_s: float = 5.0) -> None:
        self.window_ns = int(window_s * 1e9)
        self._candidates: deque[tuple[int, int]] = deque()  # (arrival_ns, offset), offsets increasing

    def reset(self) -> None:
        self._candidates.clear()

    def stamp(self, tracker_ns: int, arrival_ns: int) -> int:
        offset = arrival_ns - tracker_ns
        while self._candidates and self._candidates[-1][1] >= offset:
            self._candidates.pop()
        self._candidates.append((arrival_ns, offset))
        while self._candidates[0][0] < arrival_ns - self.window_ns:
            self._candidates.popleft()
        return tracker_ns + self._candidates[0][1]


class FrameNumbers:
    """The tracker's frame numbers, kept increasing. After a silence of ``RESUME_GAP_S`` (a reconnection), a tracker
    that restarted its count continues from the last number plus the frames the silence lasted, so downstream nodes
    count the gap as drops; otherwise a number at or below the last one is a stale duplicate and is dropped."""

    def __init__(self) -> None:
        self.shift = 0
        self.last: int | None = None
        self.last_arrival_ns = 0

    def number(self, tracker_frame: int, arrival_ns: int, rate: float) -> int | None:
        frame = tracker_frame + self.shift
        if self.last is not None and frame <= self.last:
            silence_s = (arrival_ns - self.last_arrival_ns) / 1e9
            if silence_s < RESUME_GAP_S:
                return None
            self.shift = self.last + max(1, round(silence_s * rate)) - tracker_frame
            frame = tracker_frame + self.shift
        self.last, self.last_arrival_ns = frame, arrival_ns
        return frame


class LabelRows:
    """A labelled stream's fixed row order: a label keeps its row, a new one is appended."""

    def __init__(self) -> None:
        self.labels: list[str] = []
        self._row: dict[str, int] = {}

    def rows(self, names: Sequence[str]) -> np.ndarray:
        for name in names:
            if name not in self._row:
                self._row[name] = len(self.labels)
                self.labels.append(name)
        return np.fromiter((self._row[n] for n in names), dtype=int, count=len(names))

    @staticmethod
    def clean(raw: Sequence[str]) -> list[str]:
        """Vendor names (``Subject:Marker``) cleaned the way marker files are read."""
        return clean_labels(raw, strip_prefix=True)


class LiveTracker(Node[ConfigT]):
    """Base of a push-driven source: the vendor client's thread calls ``push`` for each frame; ``emit`` publishes the
    queued frames in order, waiting at most ``IDLE_WAIT_S`` for one so that a stop request is seen promptly."""

    paced = False
    outputs = {"markers": Output(MarkerFrame, doc="labelled markers, or an unlabelled point cloud")}

    def setup(self) -> None:
        self.clock = TrackerClock()
        self.numbers = FrameNumbers()
        self.rows = LabelRows()
        self.end_after_s: float | None = None
        self._queue: queue.Queue[MarkerFrame | None] = queue.Queue()
        self._last_arrival = time.monotonic()
        self._seen = False
        self._warned = False
        self._lock = threading.Lock()  # the vendor client may call from more than one thread

    def declare(self, labels: Sequence[str]) -> None:
        """The tracker's labels in their order, before frames arrive, so that rows follow the tracker's order."""
        with self._lock:
            self.rows.rows(labels)

    def push(self, tracker_frame: int, tracker_ns: int, positions: np.ndarray, labels: Sequence[str] | None,
             arrival_ns: int) -> None:
        """One tracker frame (positions in mm; ``labels`` None for a point cloud), on the client's thread."""
        with self._lock:
            self._push(tracker_frame, tracker_ns, positions, labels, arrival_ns)

    def _push(self, tracker_frame: int, tracker_ns: int, positions: np.ndarray, labels: Sequence[str] | None,
              arrival_ns: int) -> None:
        if self.numbers.last is not None and (arrival_ns - self.numbers.last_arrival_ns) / 1e9 >= RESUME_GAP_S:
            self.clock.reset()  # a restarted tracker has a new clock
        frame = self.numbers.number(tracker_frame, arrival_ns, self.rate)
        if frame is None:
            return
        if labels is not None:
            rows = self.rows.rows(labels)
            full = np.full((len(self.rows.labels), 3), np.nan)
            full[rows] = positions
            positions, labels = full, list(self.rows.labels)
        self._queue.put(MarkerFrame(frame=frame, capture_ns=self.clock.stamp(tracker_ns, arrival_ns), rate=self.rate,
                                    positions=positions, labels=labels))

    def end(self) -> None:
        """The tracker said its capture is over: the stream ends once the queued frames are out."""
        self._queue.put(None)

    def emit(self, index: int) -> bool:
        try:
            message = self._queue.get(timeout=IDLE_WAIT_S)
        except queue.Empty:
            silence = time.monotonic() - self._last_arrival
            if self._seen and self.end_after_s is not None and silence > self.end_after_s:
                self.log.info("no frame for %.1f s: end of stream", silence)
                return False
            if silence > WARN_SILENCE_S and not self._warned:
                self.log.warning("no frame from the tracker for %.0f s; still waiting", silence)
                self._warned = True
            self.idle(silence)
            return True
        if message is None:
            return False
        self._last_arrival, self._seen, self._warned = time.monotonic(), True, False
        self.publish("markers", message)
        return True

    def idle(self, silence_s: float) -> None:
        """Called while no frame arrives (``silence_s`` since the last one): adapters ask the server again here."""
