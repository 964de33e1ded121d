"""A test node that handles each frame slowly and writes the frame numbers it handled, to watch inbox policies."""

from __future__ import annotations

import time
from pathlib import Path

from pydantic import BaseModel

from mocapflow.messages import MarkerFrame
from mocapflow.runtime.node import Input, Node


class SlowSinkConfig(BaseModel):
    path: str
    delay_s: float = 0.02


class SlowSink(Node[SlowSinkConfig]):
    """Sleeps ``delay_s`` per frame; writes the handled frame numbers, one a line, when the stream ends."""

    Config = SlowSinkConfig
    inputs = {"markers": Input(MarkerFrame)}

    def setup(self) -> None:
        self.frames: list[int] = []

    def process(self, port: str, message: MarkerFrame) -> None:
        time.sleep(self.config.delay_s)
        self.frames.append(message.frame)

    def finish(self) -> None:
        Path(self.config.path).write_text("".join(f"{f}\n" for f in self.frames))
