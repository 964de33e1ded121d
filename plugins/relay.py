"""Relay: republishes a marker stream unchanged under its own key (bridging, fan-out points, per-hop cost)."""

from __future__ import annotations

from mocapflow.messages import MarkerFrame
from mocapflow.runtime.node import Input, Node, Output


class Relay(Node):
    """Forwards every marker frame unchanged."""

    inputs = {"markers": Input(MarkerFrame)}
    outputs = {"markers": Output(MarkerFrame)}

    def process(self, port: str, message: MarkerFrame) -> None:
        self.publish("markers", message)
