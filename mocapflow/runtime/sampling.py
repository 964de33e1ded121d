"""A model stage's sample of a stream: every ``stride``-th frame, so that it sees about ``hz`` frames a second
whatever the tracker's rate (its statistics and solves need the motion, not every frame of it)."""

from __future__ import annotations


class Sampler:
    """Which frames of a stream at ``rate`` to take for about ``hz`` a second (every frame of a slower stream): the
    first, then every ``stride``-th. ``rate`` is the samples' own rate."""

    def __init__(self, rate: float, hz: float) -> None:
        self.stride = max(1, round(rate / hz))
        self.rate = rate / self.stride
        self._count = 0

    def take(self) -> bool:
        """Whether the next frame is a sample."""
        self._count += 1
        return (self._count - 1) % self.stride == 0
