"""Rerun sink: the live capture as a 3D scene to orbit, pause and scrub, in Rerun's native or web viewer or an .rrd."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from mocapflow.io.scene import Scene, blueprint, close_stream, open_stream
from mocapflow.messages import MarkerFrame, Message, NodeStats, Pose, Segments, Skeleton
from mocapflow.runtime.node import Input, Node

EARLY = 0.8
"""A frame is due a fifth of a period early: frames that come at the display rate (a preview's) are all drawn, in
spite of jitter."""


class RerunConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    spawn: bool = Field(default=False, description="start Rerun's native viewer on this machine")
    connect: str | None = Field(default=None, description="send to a running viewer at this gRPC URL, e.g. "
                                                          "rerun+http://HOST:9876/proxy")
    serve: bool = Field(default=False, description="serve the scene over gRPC and the web viewer over HTTP")
    grpc_port: int = Field(default=9876, ge=1, le=65535, description="port of the spawned viewer or of the server")
    web_port: int = Field(default=9090, ge=1, le=65535, description="web viewer port when serving")
    save: str | None = Field(default=None, description="write the scene to this .rrd file")
    rate: float | None = Field(default=60.0, gt=0, description="display rate, Hz; frames in between are skipped "
                               "(null: every frame received: the preview's, up to 60 a second; with 'queue: "
                               "{markers: all, pose: all}' on the node, every frame of the streams, even when the "
                               "viewer falls behind)")
    memory_limit: str = Field(default="1GiB", description="memory of the spawned viewer or server; beyond it the "
                                                          "oldest data is dropped")
    up: Literal["+Z", "+Y", "+X", "-Z", "-Y", "-X"] = Field(default="+Z", description="the capture's up axis")
    ray_length_mm: float = Field(default=4000.0, gt=0, description="length drawn of a ray with no position on it")

    @field_validator("save")
    @classmethod
    def _suffix(cls, path: str | None) -> str | None:
        if path is not None and Path(path).suffix.lower() != ".rrd":
            raise ValueError(f"{path!r}: the scene is saved as a .rrd file")
        return path

    @model_validator(mode="after")
    def _somewhere(self) -> RerunConfig:
        if not (self.spawn or self.connect or self.serve or self.save):
            raise ValueError("nowhere to show the scene: set spawn, connect, serve or save")
        return self


class RerunSink(Node[RerunConfig]):
    """Draws markers (coloured by segment, and by flag where estimated), rays, joint centres and bones at up to
    ``rate`` frames a second, and, linked to ``_stats/*``, each node's latency and rate as time series beside the
    scene. Its frame inputs take the streams' previews (``queue: preview``: the newest frame, at most 60 a second, so
    that a 1000 Hz stream is neither encoded nor sent for the viewer at its full rate), and frames that arrive faster
    than ``rate`` are passed over undecoded (the last one is still shown), so the viewer never holds the pipeline
    back."""

    Config = RerunConfig
    inputs = {
        "markers": Input(MarkerFrame, doc="markers to draw", queue="preview"),
        "pose": Input(Pose, required=False, doc="joint centres and bones to draw", queue="preview"),
        "skeleton": Input(Skeleton, required=False, state=True, doc="joint tree for the bones"),
        "segments": Input(Segments, required=False, state=True, doc="marker colours by segment"),
        "health": Input(NodeStats, required=False, state=True, doc="node latency and rate: link to '_stats/*'"),
    }

    def setup(self) -> None:
        config = self.config
        self.stream = open_stream(self.name, spawn=config.spawn, connect=config.connect, serve=config.serve,
                                  save=config.save, memory_limit=config.memory_limit, grpc_port=config.grpc_port,
                                  web_port=config.web_port)
        self.scene = Scene(self.stream, up=config.up, ray_length_mm=config.ray_length_mm)
        self.period = 1.0 / config.rate if config.rate else 0.0
        self.due: dict[str, float] = {}
        self.health_shown = False

    def wanted(self, port: str) -> bool:
        """A frame when one is due at the display rate; the runtime passes the others over undecoded and hands over
        the last one passed over at the end of the stream."""
        return self.config.rate is None or time.monotonic() >= self.due.get(port, 0.0)

    def process(self, port: str, message: Message) -> None:
        self.process_batch(port, [message])

    def process_batch(self, port: str, messages: list[Message]) -> None:
        if port == "health":
            if not self.health_shown:  # lay out the time series beside the scene once there is health to show
                self.stream.send_blueprint(blueprint(health=True))
                self.health_shown = True
            for stats in messages:
                self.scene.log(port, stats, time.time_ns())
            return
        if self.inputs[port].state or self.config.rate is None:
            for message in messages:
                self.scene.log(f"world/{port}", message)
            return
        self.due[port] = time.monotonic() + EARLY * self.period
        self.scene.log(f"world/{port}", messages[-1])

    def finish(self) -> None:
        problem = close_stream(self.stream)
        if problem:
            self.log.warning("the scene's last frames were not delivered: %s", problem)
