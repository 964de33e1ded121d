"""A stream's preview: at most ``PREVIEW_HZ`` of its messages a second, for those who only show it.

A viewer draws 60 frames a second at most; handed a 1000 Hz stream it would receive, and its router forward, all 1000
for nothing, and a node would encode every frame of an output only a viewer reads. So each node also publishes, only
while someone subscribes to it, a preview of each data output (``keys.PREVIEW``): the newest message whenever one
is due, the stream's last message before its end, then the end. An input with ``queue: preview`` (the ``rerun``
sink's frames by default) subscribes to the preview instead of the stream. Transport-free: ``send`` carries what is
due.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Final, Generic, TypeVar

PREVIEW_HZ: Final = 60.0
"""Messages a second, at most, in a preview: a display's rate."""

T = TypeVar("T")


class Preview(Generic[T]):
    """Thins a stream to at most ``hz`` messages a second, keeping the newest: ``offer`` each message in order,
    ``end`` when the stream ends (the last message offered is then sent, if it was held back)."""

    def __init__(self, send: Callable[[T], None], hz: float = PREVIEW_HZ) -> None:
        self._send = send
        self._period = 1.0 / hz
        self._due = 0.0
        self._held: T | None = None

    def offer(self, message: T) -> None:
        now = time.monotonic()
        if now < self._due:
            self._held = message
            return
        self._due = now + self._period
        self._held = None
        self._send(message)

    def end(self) -> None:
        if self._held is not None:
            self._send(self._held)
            self._held = None
