"""Samples of a stream by frame number, for the stages that need its motion, not every frame of it.

A publisher sends each data output also as a sampled copy (``keys.SAMPLED``): the frames whose number is a multiple
of ``base_stride(rate)``, about ``SAMPLED_HZ`` a second, while someone subscribes to it. A model stage takes every
``Sampler.stride``-th frame by number, a multiple of that stride: the same frames whether it reads the whole stream
(inside a node group, or offline) or the sampled copy from another process, so every layout gives the same model.
"""

from __future__ import annotations

SAMPLED_HZ = 120.0
"""About how many frames a second a sampled copy carries (every frame of a slower stream)."""


def base_stride(rate: float | None) -> int:
    """The sampled copy's stride for a stream at ``rate`` Hz (1: every frame, also when the rate is unknown)."""
    return max(1, round(rate / SAMPLED_HZ)) if rate else 1


def in_copy(frame: int, rate: float | None) -> bool:
    """Whether frame number ``frame`` of a stream at ``rate`` Hz is in the stream's sampled copy."""
    return frame % base_stride(rate) == 0


class Sampler:
    """Which frames of a stream a stage takes for about ``hz`` a second: those whose number is a multiple of a
    stride that the sampled copy's divides (so at most ``SAMPLED_HZ`` a second; every frame of a slower stream)."""

    def __init__(self, hz: float) -> None:
        self.hz = hz
        self._strides: dict[float, int] = {}

    def stride(self, rate: float) -> int:
        """The stride for a stream at ``rate`` Hz."""
        stride = self._strides.get(rate)
        if stride is None:
            base = base_stride(rate)
            stride = self._strides[rate] = base * max(1, round(rate / base / self.hz))
        return stride

    def rate(self, rate: float) -> float:
        """The samples' own rate, of a stream at ``rate`` Hz."""
        return rate / self.stride(rate)

    def take(self, frame: int, rate: float) -> bool:
        """Whether frame number ``frame`` of a stream at ``rate`` Hz is a sample."""
        return frame % self.stride(rate) == 0
