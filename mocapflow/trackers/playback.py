"""A marker file played in real time, for the stand-in tracker servers: which frame is due when."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass

import numpy as np

from mocapflow.io.markers import MarkerData


@dataclass(frozen=True)
class Due:
    index: int  # frames since the start (keeps rising when looping)
    frame: int  # the frame number sent: the file's own first frame plus ``index``
    positions: np.ndarray  # N x 3 mm, NaN = missing
    time_s: float  # capture time: seconds since the start on the file's own clock (index / rate)


class Playback:
    """Frame ``i`` is sent ``i / (rate * speed)`` seconds after the start (a late frame at once), stamped with its
    capture time ``i / rate``: at speed 1 the stamps run with this machine's clock, as a tracker's do."""

    def __init__(self, data: MarkerData, speed: float = 1.0, loop: bool = False) -> None:
        self.data, self.speed, self.loop = data, speed, loop

    async def frames(self) -> AsyncIterator[Due]:
        start = time.monotonic()
        period = 1.0 / (self.data.rate * self.speed)
        n = len(self.data.positions)
        index = 0
        while self.loop or index < n:
            due = start + index * period
            delay = due - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            yield Due(index, self.data.first_frame + index, self.data.positions[index % n], index / self.data.rate)
            index += 1
