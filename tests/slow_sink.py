"""A test node that handles frames slowly, or only some of them, and writes the frame numbers it handled, to watch
inbox policies and sampling; and what its process's garbage collector watches."""

from __future__ import annotations

import gc
import time
from pathlib import Path

from pydantic import BaseModel

from mocapflow.messages import MarkerFrame
from mocapflow.runtime.node import Input, Node


class SlowSinkConfig(BaseModel):
    path: str
    delay_s: float = 0.02
    every: int = 1  # wants one message of every ``every`` (``Node.wanted``), the first one included


class SlowSink(Node[SlowSinkConfig]):
    """Sleeps ``delay_s`` per frame it wants; writes the handled frame numbers, one a line, when the stream ends, their
    capture times (ns) to ``path`` + ``.capture``, and to ``path`` + ``.gc`` the objects its process's garbage collector
    has frozen and those it still tracks."""

    Config = SlowSinkConfig
    inputs = {"markers": Input(MarkerFrame)}

    def setup(self) -> None:
        self.frames: list[int] = []
        self.captures: list[int] = []
        self.offered = 0

    def wanted(self, port: str) -> bool:
        self.offered += 1
        return (self.offered - 1) % self.config.every == 0

    def process(self, port: str, message: MarkerFrame) -> None:
        time.sleep(self.config.delay_s)
        self.frames.append(message.frame)
        self.captures.append(message.capture_ns)

    def finish(self) -> None:
        Path(self.config.path).write_text("".join(f"{f}\n" for f in self.frames))
        Path(self.config.path + ".capture").write_text("".join(f"{t}\n" for t in self.captures))
        Path(self.config.path + ".gc").write_text(f"{gc.get_freeze_count()} {len(gc.get_objects())}\n")
