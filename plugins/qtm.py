"""Qualisys Track Manager tracker over QTM's real-time protocol, through Qualisys's own Python SDK (``qtm-rt``).

Install with ``pip install 'mocapflow[qualisys]'``. The SDK's asyncio client runs on a thread of the node: it reads the
capture rate (General/Frequency) and the 3D labels (The_3D/Label/Name) from QTM's parameters, streams the ``3d``
(labelled, NaN for a label not seen) or ``3dnolabels`` (point cloud) component, and hands each packet to the node.
QTM's frame numbers and microsecond timestamps become the frames' numbers and capture times (mapped to this machine's
clock, see ``mocapflow.trackers.live``). A lost connection is retried every ``retry_s`` while the graph runs.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
import xml.etree.ElementTree as ET
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mocapflow.trackers.live import LabelRows, LiveTracker

UNIT_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
logging.getLogger("qtm_rt").setLevel(logging.CRITICAL)  # the SDK logs each failure; this node reports them itself


class QtmConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    host: str = Field(default="127.0.0.1", description="address of the PC running QTM")
    port: int = Field(default=22223, ge=1, le=65535, description="QTM's real-time port (little endian)")
    component: Literal["3d", "3dnolabels"] = Field(
        default="3d", description="3d: labelled markers; 3dnolabels: the unlabelled point cloud (link a labeller)")
    units: Literal["mm", "cm", "m"] = Field(default="mm", description="unit of QTM's 3D positions (mm unless changed)")
    divisor: int = Field(default=1, ge=1, description="stream every n-th captured frame (1: all frames); frames are "
                         "then numbered QTM's number // n")
    timeout_s: float = Field(default=5.0, gt=0, description="how long to wait for QTM to answer or stream")
    retry_s: float = Field(default=1.0, gt=0, description="pause between reconnection attempts")
    end_with_capture: bool = Field(
        default=False, description="end the stream when QTM reports its capture or RT-from-file playback stopped")


def read_parameters(xml: bytes | str) -> tuple[float, list[str]]:
    """Capture rate and 3D labels from QTM's ``getparameters general 3d`` answer."""
    root = ET.fromstring(xml)
    frequency = root.findtext("General/Frequency")
    if frequency is None:
        raise ValueError("QTM's parameters have no General/Frequency")
    return float(frequency), [label.findtext("Name") or "" for label in root.findall("The_3D/Label")]


class QtmTracker(LiveTracker[QtmConfig]):
    """Markers streamed live by Qualisys QTM (real-time protocol, through Qualisys's qtm-rt SDK)."""

    Config = QtmConfig

    def setup(self) -> None:
        super().setup()
        self.scale = UNIT_MM[self.config.units]
        self.labels: list[str] = []
        self._loop = asyncio.new_event_loop()
        self._stop = asyncio.Event()
        self._ready = threading.Event()
        self._failure: Exception | None = None
        self._thread = threading.Thread(target=self._loop.run_until_complete, args=(self._run(),), daemon=True,
                                        name="qtm")
        self._thread.start()
        if not self._ready.wait(self.config.timeout_s * 3):
            self._failure = ConnectionError(f"{self.where} did not answer within {self.config.timeout_s * 3:g} s")
        if self._failure is not None:
            self.finish()
            raise self._failure
        self.log.info("QTM at %s:%d: %g Hz, %s, %d labels", self.config.host, self.config.port, self.rate,
                      self.config.component, len(self.labels))

    @property
    def where(self) -> str:
        return f"QTM at {self.config.host}:{self.config.port}"

    async def _run(self) -> None:
        import qtm_rt

        first = True
        while not self._stop.is_set():
            lost = asyncio.Event()
            connection = None
            try:
                connection = await qtm_rt.connect(
                    self.config.host, self.config.port, timeout=self.config.timeout_s,
                    on_disconnect=lambda _exc, lost=lost: lost.set(), on_event=self._on_event)
                if connection is None:
                    raise ConnectionError(f"{self.where} is unreachable (is QTM running with real-time output on "
                                          f"port {self.config.port}?)")
                self.rate, raw = read_parameters(await connection.get_parameters(["general", "3d"]))
                self.labels = LabelRows.clean(raw)
                self.declare(self.labels)
                self.rate /= self.config.divisor
                frames = "allframes" if self.config.divisor == 1 else f"frequencydivisor:{self.config.divisor}"
                try:
                    await connection.stream_frames(frames=frames, components=[self.config.component],
                                                   on_packet=self._on_packet)
                except TimeoutError:
                    raise ConnectionError(f"{self.where} streams no frames (start a measurement or RT from "
                                          "file in QTM)") from None
            except Exception as exc:
                if connection is not None and connection.has_transport():
                    connection.disconnect()
                if first:
                    self._failure = exc if isinstance(exc, ConnectionError) else ConnectionError(f"{self.where}: {exc}")
                    self._ready.set()
                    return
                self.log.warning("%s: %s; retrying in %g s", self.where, exc, self.config.retry_s)
                await self._pause(self.config.retry_s)
                continue
            if first:
                self._ready.set()
                first = False
            stop, dropped = asyncio.ensure_future(self._stop.wait()), asyncio.ensure_future(lost.wait())
            await asyncio.wait([stop, dropped], return_when=asyncio.FIRST_COMPLETED)
            stop.cancel()
            dropped.cancel()
            if self._stop.is_set():
                if connection is not None and connection.has_transport():
                    await connection.stream_frames_stop()
                    connection.disconnect()
                return
            self.log.warning("%s: connection lost; reconnecting", self.where)
            await self._pause(self.config.retry_s)

    async def _pause(self, seconds: float) -> None:
        try:
            await asyncio.wait_for(self._stop.wait(), seconds)
        except TimeoutError:
            pass

    def _on_packet(self, packet: object) -> None:
        arrival_ns = time.time_ns()
        if self.config.component == "3d":
            _, markers = packet.get_3d_markers()  # type: ignore[attr-defined]
            positions = np.array(markers, dtype=float).reshape(-1, 3)
            labels: list[str] | None = self.labels
            if len(self.labels) != len(positions):  # not as many markers as labels: name them by position
                labels = LabelRows.clean([*self.labels, *[""] * len(positions)][:len(positions)])
        else:
            _, markers = packet.get_3d_markers_no_label()  # type: ignore[attr-defined]
            positions = np.array([m[:3] for m in markers], dtype=float).reshape(-1, 3)
            positions = positions[np.isfinite(positions).all(axis=1)]
            labels = None
        # with a divisor, QTM's numbers step by it: number the streamed frames 1 apart, so no stage counts drops
        self.push(packet.framenumber // self.config.divisor, int(packet.timestamp) * 1000,  # type: ignore
                  positions * self.scale, labels, arrival_ns)

    def _on_event(self, event: object) -> None:
        import qtm_rt

        if self.config.end_with_capture and event in (qtm_rt.QRTEvent.EventCaptureStopped,
                                                      qtm_rt.QRTEvent.EventRTfromFileStopped):
            self.log.info("%s: %s, end of stream", self.where, getattr(event, "name", event))
            self.end()
            self._loop.call_soon(self._stop.set)

    def finish(self) -> None:
        if self._loop.is_running():
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(timeout=5)
        if not self._thread.is_alive():
            self._loop.close()
