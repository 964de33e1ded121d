"""A test source that logs, in order, each frame it is asked to prepare and each frame it emits, to watch when the
runtime calls ``Node.prepare``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import BaseModel

from mocapflow.messages import MarkerFrame
from mocapflow.runtime.node import Node, Output


class PreparedSourceConfig(BaseModel):
    path: str
    rate: float = 50.0
    frames: int = 50


class PreparedSource(Node[PreparedSourceConfig]):
    """Emits ``frames`` one-marker frames at ``rate``; writes ``prepare N`` and ``emit N`` lines, in the order the
    calls came, to ``path`` when it finishes."""

    Config = PreparedSourceConfig
    outputs = {"markers": Output(MarkerFrame)}

    def setup(self) -> None:
        self.rate = self.config.rate
        self.calls: list[str] = []

    def prepare(self, index: int) -> None:
        self.calls.append(f"prepare {index}")

    def emit(self, index: int) -> bool:
        if index >= self.config.frames:
            return False
        self.calls.append(f"emit {index}")
        self.publish("markers", MarkerFrame(frame=index, capture_ns=self.due_ns(index), rate=self.rate,
                                            positions=np.zeros((1, 3))))
        return True

    def finish(self) -> None:
        Path(self.config.path).write_text("\n".join(self.calls) + "\n")
