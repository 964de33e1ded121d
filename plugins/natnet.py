"""OptiTrack Motive tracker over NatNet, through the ``natnet`` package (a port of OptiTrack's NatNetClient.py).

Install with ``pip install 'mocapflow[optitrack]'``. The client's threads receive Motive's frames and data
descriptions; labelled markers are named ``Asset:Marker`` from the descriptions (the asset, rigid body or skeleton,
whose id is the high half of a labelled marker's id, and the marker set of that name, whose n-th marker is the low
half), then cleaned like file labels. The unlabelled mode publishes every labelled-markers entry (Motive lists each
reconstructed marker there, labelled or not) as a point cloud. Positions are converted from metres to mm; a marker
Motive flags as occluded (its position solved from the asset's model) is published as missing unless
``occluded: keep``. Frame numbers are Motive's; capture times come from its timestamp (seconds on Motive's clock),
mapped to this machine's clock. While Motive is silent the node asks it again every second (NAT_CONNECT and the
descriptions), so a restarted Motive or a dropped network resumes the stream.
"""

from __future__ import annotations

import socket
import threading
import time
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mocapflow.trackers.live import RESUME_GAP_S, LabelRows, LiveTracker

OCCLUDED = 0x01
RECEIVE_BUFFER = 4 << 20
"""Bytes of socket buffer for frames that arrive while the client's thread is held up (a busy machine): about two
seconds of a 40-marker stream at 240 Hz, where the system default holds a few hundred milliseconds."""


def enlarge_receive_buffers(client: Any) -> None:
    """Room for frames that arrive while the client's thread is held up. The client keeps its sockets private;
    frames come on the data socket (multicast) or the command socket (unicast). The system caps the size at
    net.core.rmem_max."""
    for kind in ("data", "command"):
        sock = getattr(client, f"_NatNetClient__{kind}_socket", None)
        if isinstance(sock, socket.socket):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER)


class NatNetConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    server: str = Field(default="127.0.0.1", description="address of the PC running Motive")
    local: str = Field(default="127.0.0.1", description="this machine's address on the network to Motive")
    multicast: bool = Field(default=True, description="Motive's transmission type: multicast (its default) or "
                            "unicast (false)")
    multicast_address: str = Field(default="239.255.42.99", description="Motive's multicast group")
    command_port: int = Field(default=1510, ge=1, le=65535, description="Motive's command port")
    data_port: int = Field(default=1511, ge=1, le=65535, description="Motive's data port (multicast)")
    markers: Literal["labelled", "unlabelled"] = Field(
        default="labelled", description="labelled: markers of Motive's assets, named; unlabelled: every marker as a "
        "point cloud (link a labeller)")
    occluded: Literal["missing", "keep"] = Field(
        default="missing", description="markers Motive solved from its model while occluded: missing (mocapflow's "
        "filler decides) or keep Motive's position")
    rate: float | None = Field(default=None, gt=0, description="capture rate in Hz (none: from the frames' "
                               "timestamps)")
    timeout_s: float = Field(default=5.0, gt=0, description="how long to wait for Motive to answer and stream")
    end_after_s: float | None = Field(default=None, gt=0, description="end the stream after this long without a "
                                      "frame (for replays; none: keep waiting)")


class NatNetTracker(LiveTracker[NatNetConfig]):
    """Markers streamed live by OptiTrack Motive (NatNet, through the natnet package)."""

    Config = NatNetConfig

    def setup(self) -> None:
        super().setup()
        from natnet import NatNetClient

        self.end_after_s = self.config.end_after_s
        self.names: dict[int, str] = {}
        self._asked = time.monotonic()
        self._first: Any = None
        self._held: list[tuple[Any, int]] = []  # labelled frames that came before the names
        self._hold_until = time.monotonic() + self.config.timeout_s
        self._hold_lock = threading.RLock()
        config = self.config
        self.client = NatNetClient(server_ip_address=config.server, local_ip_address=config.local,
                                   multicast_address=config.multicast_address, command_port=config.command_port,
                                   data_port=config.data_port, use_multicast=config.multicast)
        self.client.on_data_description_received_event.handlers.append(self._on_descriptions)
        self.client.on_data_frame_received_event.handlers.append(self._on_frame)
        try:
            self.client.connect(timeout=self.config.timeout_s)
        except TimeoutError:
            raise ConnectionError(f"no NatNet server answered at {self.where} within {self.config.timeout_s:g} s (is "
                                  "Motive streaming, with this transmission type?)") from None
        except OSError as exc:
            raise ConnectionError(f"NatNet at {self.where}: {exc}") from None
        enlarge_receive_buffers(self.client)
        self.client.request_modeldef()
        self.rate = self.config.rate or 0.0
        self.client.run_async()
        deadline = time.monotonic() + self.config.timeout_s
        while (self.numbers.last is None or (self.config.markers == "labelled" and not self.names)) \
                and time.monotonic() < deadline:
            time.sleep(0.01)
        if self.numbers.last is None:
            self.client.shutdown()
            raise ConnectionError(f"NatNet server at {self.where} streams no frames (is streaming enabled in Motive?)")
        info = self.client.server_info
        self.log.info("NatNet at %s: %s, NatNet %s, %g Hz, %s markers", self.where,
                      info.application_name if info else "?", self.client.protocol_version, self.rate,
                      self.config.markers)

    @property
    def where(self) -> str:
        return f"{self.config.server}:{self.config.command_port}"

    def _on_descriptions(self, descriptions: Any) -> None:
        marker_sets = {m.name: m.marker_names for m in descriptions.marker_sets}
        assets = [(d.id_num, d.name) for d in (*descriptions.rigid_bodies, *descriptions.skeletons)]
        raw = {(model << 16) | (k + 1): f"{asset}:{marker}" for model, asset in assets
               for k, marker in enumerate(marker_sets.get(asset, ()))}
        self.names = dict(zip(raw, LabelRows.clean(list(raw.values())), strict=True))
        with self._hold_lock:
            self.declare(list(self.names.values()))
            held, self._held = self._held, []
            for frame, arrival_ns in held:
                self._convert(frame, arrival_ns)

    def _on_frame(self, frame: Any) -> None:
        arrival_ns = time.time_ns()
        if not self.rate:  # no rate configured: from the spacing of the first two frames' timestamps
            if self._first is None:
                self._first = (frame, arrival_ns)
                return
            first = self._first[0]
            if frame.suffix.timestamp <= first.suffix.timestamp:
                return
            self.rate = round((frame.prefix.frame_number - first.prefix.frame_number)
                              / (frame.suffix.timestamp - first.suffix.timestamp), 3)
            self._convert(*self._first)
        self._convert(frame, arrival_ns)

    def _convert(self, frame: Any, arrival_ns: int) -> None:
        with self._hold_lock:
            if self.config.markers == "labelled" and not self.names and time.monotonic() < self._hold_until:
                self._held.append((frame, arrival_ns))
                return
        if frame.suffix.tracked_models_changed:
            self.client.request_modeldef()
        keep = self.config.occluded == "keep"
        markers = [m for m in frame.labeled_markers if keep or not m.param & OCCLUDED]
        labels: list[str] | None = None
        if self.config.markers == "labelled":
            markers = [m for m in markers if m.model_id != 0]
            labels = [self.names.get(m.id_num) or f"{m.model_id}_{m.marker_id}" for m in markers]
        positions = np.array([m.pos for m in markers], dtype=float).reshape(-1, 3) * 1000.0
        self.push(frame.prefix.frame_number, round(frame.suffix.timestamp * 1e9), positions, labels, arrival_ns)

    def idle(self, silence_s: float) -> None:
        if silence_s > RESUME_GAP_S and time.monotonic() - self._asked > 1.0:  # Motive restarted or the network dropped
            self._asked = time.monotonic()
            self.client.send_request(self.client.NAT_CONNECT)
            self.client.request_modeldef()

    def finish(self) -> None:
        self.client.shutdown()
