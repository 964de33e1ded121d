"""A stand-in for OptiTrack Motive's NatNet server (protocol 3.0, unicast), playing a marker file or a recorded
session: what ``mocapflow serve natnet`` runs. Written from the NatNet SDK's packet layouts (little-endian; every
message is ``id`` uint16, ``size`` uint16, payload): a client's NAT_CONNECT on the command port is answered with
NAT_SERVERINFO (application name, versions, the high-resolution clock's frequency) and registers the client for
frames; NAT_REQUEST_MODELDEF is answered with NAT_MODELDEF (a marker set named after the file with its labels, and a
skeleton of that name, id 1, whose labelled markers are numbered 1..N); frames go to every registered client as
NAT_FRAMEOFDATA: frame number, the marker set's positions (metres, NaN when not seen), the labelled markers seen
(id ``1 << 16 | n``, size, params, residual), the timestamp in seconds and the camera mid-exposure, data-received and
transmit times in clock ticks. A client that sends nothing (keep-alive included) for ``CLIENT_TIMEOUT_S`` is dropped.

Given a packet capture (.pcapng) of a real session instead of a marker file, the server answers with the capture's
own server info and model definitions and sends its recorded frames with their recorded timing.
"""

from __future__ import annotations

import asyncio
import logging
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mocapflow.io.markers import MarkerData
from mocapflow.io.pcapng import read_udp
from mocapflow.trackers.playback import Due, Playback

CONNECT, SERVERINFO, REQUEST, RESPONSE, REQUEST_MODELDEF, MODELDEF, FRAMEOFDATA, KEEPALIVE = 0, 1, 2, 3, 4, 5, 7, 10
CLOCK_HZ = 10_000_000
CLIENT_TIMEOUT_S = 10.0
SKELETON_ID = 1
MARKER_SIZE_M = 0.014
PC_SOLVED = 0x02

log = logging.getLogger("mocapflow.serve.natnet")


def message(kind: int, payload: bytes) -> bytes:
    return struct.pack("<HH", kind, len(payload)) + payload


def cstring(value: str) -> bytes:
    return value.encode() + b"\0"


def server_info(data_port: int) -> bytes:
    name = b"mocapflow serve natnet".ljust(256, b"\0")
    return message(SERVERINFO, name + bytes([0, 1, 0, 0]) + bytes([3, 0, 0, 0])
                   + struct.pack("<QH?4s", CLOCK_HZ, data_port, False, bytes([239, 255, 42, 99])))


def model_definitions(name: str, labels: list[str]) -> bytes:
    marker_set = struct.pack("<I", 0) + cstring(name) + struct.pack("<I", len(labels)) + b"".join(map(cstring, labels))
    skeleton = struct.pack("<I", 2) + cstring(name) + struct.pack("<II", SKELETON_ID, 0)
    return message(MODELDEF, struct.pack("<I", 2) + marker_set + skeleton)


def frame_of_data(due: Due, name: str) -> bytes:
    metres = due.positions / 1000.0
    seen = np.flatnonzero(np.isfinite(due.positions).all(axis=1))
    labelled = np.zeros(len(seen), dtype=[("id", "<u4"), ("xyz", "<f4", 3), ("size", "<f4"), ("params", "<u2"),
                                          ("residual", "<f4")])
    labelled["id"] = (SKELETON_ID << 16) | (seen + 1)
    labelled["xyz"], labelled["size"], labelled["params"] = metres[seen], MARKER_SIZE_M, PC_SOLVED
    ticks = round(due.time_s * CLOCK_HZ)
    body = (struct.pack("<II", due.frame, 1) + cstring(name) + struct.pack("<I", len(metres))
            + metres.astype("<f4").tobytes()
            + struct.pack("<III", 0, 0, 0)  # other markers, rigid bodies, skeletons
            + struct.pack("<I", len(seen)) + labelled.tobytes()
            + struct.pack("<II", 0, 0)  # force plates, devices
            + struct.pack("<IIdQQQH", 0, 0, due.time_s, ticks, ticks, round(time.monotonic() * CLOCK_HZ), 0)
            + struct.pack("<I", 0))  # end of data
    return message(FRAMEOFDATA, body)


@dataclass(frozen=True)
class Recording:
    """A recorded session: the server's own answers and its frames with their times (seconds from the first)."""

    server_info: bytes
    model_definitions: bytes
    frames: list[tuple[float, bytes]]

    @classmethod
    def read(cls, path: str | Path) -> Recording:
        packets = read_udp(path)
        first: dict[int, bytes] = {}
        frames = []
        for p in packets:
            kind = struct.unpack_from("<H", p.payload)[0] if len(p.payload) >= 4 else -1
            if kind == FRAMEOFDATA:
                frames.append((p.time_s, p.payload))
            elif kind in (SERVERINFO, MODELDEF):
                first.setdefault(kind, p.payload)
        if not frames or SERVERINFO not in first:
            raise ValueError(f"{path}: no NatNet server info and frames in this capture")
        t0 = frames[0][0]
        return cls(first[SERVERINFO], first.get(MODELDEF, message(MODELDEF, struct.pack("<I", 0))),
                   [(t - t0, payload) for t, payload in frames])


class NatNetServer(asyncio.DatagramProtocol):
    """Serves ``source`` (a marker file or a recording) on the command port; frames start with the first client.
    ``on_sent(frame_number, time_ns)`` is called after each frame is sent (for latency measurements)."""

    def __init__(self, source: MarkerData | Recording, name: str = "file", speed: float = 1.0, loop: bool = False,
                 data_port: int = 1511, on_sent: Callable[[int, int], None] | None = None) -> None:
        self.source, self.name, self.speed, self.loop = source, name, speed, loop
        self.data_port, self.on_sent = data_port, on_sent
        self.clients: dict[tuple[str, int], float] = {}
        self.started = asyncio.Event()
        self.transport: asyncio.DatagramTransport | None = None

    async def serve(self, host: str, port: int, ready: Callable[[], None] | None = None) -> None:
        loop = asyncio.get_running_loop()
        await loop.create_datagram_endpoint(lambda: self, local_addr=(host, port))
        if ready is not None:
            ready()
        await self.started.wait()
        await (self._play_recording() if isinstance(self.source, Recording) else self._play_file())
        log.info("end of %s", "recording" if isinstance(self.source, Recording) else "file")
        await asyncio.Event().wait()  # keep answering clients

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        if len(data) < 4 or self.transport is None:
            return
        kind = struct.unpack_from("<H", data)[0]
        if kind == CONNECT:
            self.clients[addr] = time.monotonic()
            info = self.source.server_info if isinstance(self.source, Recording) else server_info(self.data_port)
            self.transport.sendto(info, addr)
            self.started.set()
        elif kind == REQUEST_MODELDEF:
            definitions = (self.source.model_definitions if isinstance(self.source, Recording)
                           else model_definitions(self.name, self.source.labels))
            self.transport.sendto(definitions, addr)
        elif kind == REQUEST:
            self.transport.sendto(message(RESPONSE, struct.pack("<i", 0)), addr)
        if addr in self.clients:
            self.clients[addr] = time.monotonic()

    def _send(self, payload: bytes) -> None:
        now = time.monotonic()
        for addr, heard in list(self.clients.items()):
            if now - heard > CLIENT_TIMEOUT_S:
                del self.clients[addr]
            elif self.transport is not None:
                self.transport.sendto(payload, addr)

    async def _play_file(self) -> None:
        assert isinstance(self.source, MarkerData)
        async for due in Playback(self.source, self.speed, self.loop).frames():
            self._send(frame_of_data(due, self.name))
            if self.on_sent is not None:
                self.on_sent(due.frame, time.time_ns())

    async def _play_recording(self) -> None:
        assert isinstance(self.source, Recording)
        start = time.monotonic()
        while True:
            for at, payload in self.source.frames:
                delay = start + at / self.speed - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
                self._send(payload)
                if self.on_sent is not None:
                    self.on_sent(struct.unpack_from("<I", payload, 4)[0], time.time_ns())
            if not self.loop:
                return
            start = time.monotonic() + 1 / 120
