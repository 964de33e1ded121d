"""What a node accepts from a data input: frames and end of stream only from the stream's own publisher, frame
numbers that make sense, frames of a plausible size. One place, the worker's input path, for every node.

Every sample a worker publishes carries an attachment naming its publisher, ``node@run`` (``run`` is random per
process start). On each data input the worker follows one publisher, the *owner*:

- a frame from anyone else is refused while the owner is alive (it published within ``takeover_s``); after that
  silence (the owner crashed and its replacement, with a new run id, starts) the next publisher takes over;
- end of stream (a Zenoh DELETE) ends the input only when it comes from the owner (or, before any frame, from a
  publisher naming the upstream node); any other DELETE is ignored, counted and logged;
- a frame that is not after the last accepted one is refused, so nothing is ever written over a real frame; a frame
  more than ``max_frame_jump`` ahead is refused; a stream whose counter really jumped or was reset is followed again
  once ``resync_frames`` consecutive frames agree with each other (those are the frames it costs);
- a frame of more than ``max_markers`` markers is refused; a coordinate beyond ``max_coordinate_mm`` is treated as
  missing; a frame with no coordinate left is refused.

The identity stops stray, blind or accidental traffic (another launcher, a ``zenoh delete`` typed in the wrong
terminal); a client that can read the stream can copy it, which only the router's access rules prevent
(docs/lab-deployment.md).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mocapflow.messages import MarkerFrame, Message

MAX_RATE_HZ = 100_000  # no tracker is faster: bounds how far a restarted publisher's clock can have moved
MAX_COORDINATE_MM = 1e5  # no capture volume is larger: 100 m from the origin


def beyond_volume(positions: np.ndarray, limit: float = MAX_COORDINATE_MM) -> np.ndarray:
    """Per sample of ``positions`` (its coordinates on the last axis), whether one coordinate lies beyond ``limit`` mm:
    no capture volume holds it. A missing sample (NaN) is not beyond."""
    with np.errstate(invalid="ignore"):
        return (np.abs(np.asarray(positions)) > limit).any(axis=-1)


class StreamLimits(BaseModel):
    """The graph's ``limits:`` section: what every node accepts on its data inputs."""

    model_config = ConfigDict(extra="forbid")

    max_markers: int = Field(default=5000, ge=1, description="frames with more markers are refused")
    max_frame_jump: int = Field(default=1000, ge=1, description="a frame further ahead of the last one is refused")
    resync_frames: int = Field(default=5, ge=2, description="consecutive frames that re-establish a jumped counter")
    max_coordinate_mm: float = Field(default=MAX_COORDINATE_MM, gt=0,
                                     description="coordinates beyond it are treated as missing")
    takeover_s: float = Field(default=1.0, gt=0, description="silence after which another publisher may take over")


def new_identity(node: str) -> bytes:
    """The attachment this process puts on every sample it publishes."""
    return f"{node}@{os.urandom(8).hex()}".encode()


class Refused(ValueError):
    """A sample the input does not accept; the message says why."""


@dataclass
class InputGuard:
    """The state of one data input: its owner, the last accepted frame, a resynchronisation candidate."""

    upstream: str
    limits: StreamLimits
    owner: bytes | None = None
    owner_seen: float = 0.0
    last: int | None = None
    candidate: tuple[int, int] | None = None  # (last frame of a run of refused consecutive frames, its length)
    takeover_allowance: int | None = None  # how far ahead the first frame of a new owner may be

    def accept_end(self, identity: bytes | None) -> bool:
        """Whether a DELETE from ``identity`` ends this input."""
        if self.owner is not None:
            return identity == self.owner
        return identity is not None and identity.split(b"@")[0] == self.upstream.encode()

    def check_source(self, identity: bytes | None, now: float | None = None) -> None:
        """Refuse a sample from anyone but the owner while the owner is alive."""
        now = time.monotonic() if now is None else now
        if identity != self.owner:
            if self.owner is not None and now - self.owner_seen < self.limits.takeover_s:
                who = identity.decode(errors="replace") if identity else "an anonymous publisher"
                raise Refused(f"frame from {who} while {self.owner.decode(errors='replace')} publishes this stream")
            self.takeover_allowance = (
                None if self.owner is None and self.last is None
                else self.limits.max_frame_jump + int((now - self.owner_seen) * MAX_RATE_HZ))
            self.owner, self.candidate = identity, None
        self.owner_seen = now

    def check_frame(self, message: Message) -> Message:
        """Refuse an implausible frame number or size; return the frame, beyond-bound coordinates made missing."""
        frame, last = message.frame, self.last
        # A publisher that took over (a restarted source) resumes on its clock: as far ahead as its silence allows.
        ahead = frame - last if last is not None else 1
        bound = self.limits.max_frame_jump if self.takeover_allowance is None else self.takeover_allowance
        if not 0 < ahead <= bound:
            run = self.candidate[1] + 1 if self.candidate and frame == self.candidate[0] + 1 else 1
            self.candidate = (frame, run)
            if run < self.limits.resync_frames:
                what = "not after" if ahead <= 0 else f"more than {self.limits.max_frame_jump} frames after"
                raise Refused(f"frame {frame} is {what} the last accepted frame {last}")
        if isinstance(message, MarkerFrame):
            message = self._bounded(message)
        self.last, self.candidate, self.takeover_allowance = frame, None, None
        return message

    def _bounded(self, message: MarkerFrame) -> MarkerFrame:
        n = len(message.positions)
        if n > self.limits.max_markers:
            raise Refused(f"frame {message.frame} has {n} markers (at most {self.limits.max_markers}, "
                          "limits.max_markers)")
        beyond = beyond_volume(message.positions, self.limits.max_coordinate_mm)
        if beyond.any():
            positions = np.array(message.positions, dtype=float)
            positions[beyond] = np.nan
            if n and np.isnan(positions).all():
                raise Refused(f"frame {message.frame}: every coordinate is beyond {self.limits.max_coordinate_mm:g}"
                              " mm (limits.max_coordinate_mm)")
            message = message.model_copy(update={"positions": positions})
        return message
