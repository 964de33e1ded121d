"""A stand-in for Qualisys Track Manager's real-time server, playing a marker file: what ``mocapflow serve qtm``
runs. Written from the QTM RT protocol documentation (little-endian, version 1.x): every packet is ``size`` (uint32,
header included), ``type`` (uint32), payload. On connection the server sends the command "QTM RT Interface
connected"; it answers ``Version``, ``QTMVersion``, ``ByteOrder``, ``GetState``, ``GetParameters`` (General and 3D as
XML), ``GetCurrentFrame`` and ``StreamFrames`` (AllFrames, Frequency:n, FrequencyDivisor:n; Stop) for the 3D and
3D-no-labels components. Data packets hold the capture timestamp (int64, microseconds on the server's clock), the
frame number (uint32) and the components (size, type, then for 3D: marker count, 2D drop rate, out-of-sync rate, and
x, y, z float32 in mm per label, NaN when not seen; for 3D no labels: x, y, z and a uint32 id per seen marker).

The file starts playing when the first client asks for frames; every streaming client gets the same frames. At the
end (unless looping) the server sends the "RT from file stopped" event, as QTM does after a file played in real time.
"""

from __future__ import annotations

import asyncio
import logging
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from xml.sax.saxutils import escape

import numpy as np

from mocapflow.io.markers import MarkerData
from mocapflow.trackers.playback import Due, Playback

ERROR, COMMAND, XML, DATA, NO_MORE_DATA, EVENT = 0, 1, 2, 3, 4, 6
COMPONENT_3D, COMPONENT_3D_NO_LABELS = 1, 2
EVENT_CONNECTED, EVENT_RT_FROM_FILE_STARTED, EVENT_RT_FROM_FILE_STOPPED = 1, 8, 9
COMPONENTS = {"3d": COMPONENT_3D, "3dnolabels": COMPONENT_3D_NO_LABELS}
PROTOCOL_VERSION = "1.25"

log = logging.getLogger("mocapflow.serve.qtm")


def packet(kind: int, payload: bytes) -> bytes:
    return struct.pack("<II", 8 + len(payload), kind) + payload


def text(kind: int, message: str) -> bytes:
    return packet(kind, message.encode() + b"\0")


def parameters_xml(data: MarkerData) -> str:
    labels = "".join(f"<Label><Name>{escape(name)}</Name><RGBColor>65280</RGBColor></Label>" for name in data.labels)
    return (f"<QTM_Parameters_Ver_{PROTOCOL_VERSION}><General><Frequency>{data.rate:g}</Frequency>"
            f"<Capture_Time>{len(data.positions) / data.rate:g}</Capture_Time></General>"
            f"<The_3D><AxisUpwards>+Z</AxisUpwards><Labels>{len(data.labels)}</Labels>{labels}</The_3D>"
            f"</QTM_Parameters_Ver_{PROTOCOL_VERSION}>")


def data_packet(due: Due, components: list[int]) -> bytes:
    body = b""
    for component in components:
        if component == COMPONENT_3D:
            markers = due.positions.astype("<f4").tobytes()
            count = len(due.positions)
        else:
            seen = np.flatnonzero(np.isfinite(due.positions).all(axis=1))
            rows = np.zeros(len(seen), dtype=[("xyz", "<f4", 3), ("id", "<u4")])
            rows["xyz"], rows["id"] = due.positions[seen], seen + 1
            markers, count = rows.tobytes(), len(seen)
        content = struct.pack("<Ihh", count, 0, 0) + markers
        body += struct.pack("<II", 8 + len(content), component) + content
    return packet(DATA, struct.pack("<qII", round(due.time_s * 1e6), due.frame, len(components)) + body)


@dataclass
class Client:
    writer: asyncio.StreamWriter
    components: list[int] = field(default_factory=list)
    divisor: int = 0  # 0: not streaming


class QtmServer:
    """``on_sent(frame_number, time_ns)`` is called after each frame is written (for latency measurements)."""

    def __init__(self, data: MarkerData, speed: float = 1.0, loop: bool = False,
                 on_sent: Callable[[int, int], None] | None = None) -> None:
        self.data = data
        self.playback = Playback(data, speed, loop)
        self.on_sent = on_sent
        self.clients: list[Client] = []
        self.started = asyncio.Event()
        self.ended = False
        self.current: Due | None = None

    async def serve(self, host: str, port: int, ready: Callable[[], None] | None = None) -> None:
        server = await asyncio.start_server(self._client, host, port)
        async with server:
            if ready is not None:
                ready()
            await self._play()
            await asyncio.Event().wait()  # keep answering clients after the end of the file

    async def _play(self) -> None:
        import time

        await self.started.wait()
        log.info("playing %d frames at %g Hz", len(self.data.positions), self.data.rate * self.playback.speed)
        async for due in self.playback.frames():
            self.current = due
            for client in self.clients:
                if client.divisor and due.index % client.divisor == 0:
                    client.writer.write(data_packet(due, client.components))
            if self.on_sent is not None:
                self.on_sent(due.frame, time.time_ns())
        self.ended = True
        log.info("end of file: RT from file stopped")
        for client in self.clients:
            client.divisor = 0
            client.writer.write(packet(EVENT, bytes([EVENT_RT_FROM_FILE_STOPPED])))

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        client = Client(writer)
        self.clients.append(client)
        writer.write(text(COMMAND, "QTM RT Interface connected"))
        try:
            while True:
                size, kind = struct.unpack("<II", await reader.readexactly(8))
                payload = (await reader.readexactly(size - 8)).rstrip(b"\0").decode(errors="replace")
                if kind == COMMAND:
                    try:
                        self._command(client, payload)
                    except (ValueError, IndexError):
                        writer.write(text(ERROR, f"Parse error: {payload.strip()}"))
                else:
                    writer.write(text(ERROR, "Command not supported"))
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            self.clients.remove(client)
            writer.close()

    def _command(self, client: Client, command: str) -> None:
        words = command.split()
        verb = words[0].lower() if words else ""
        write = client.writer.write
        if verb == "version":
            write(text(COMMAND, f"Version set to {words[1] if len(words) > 1 else PROTOCOL_VERSION}"))
        elif verb == "qtmversion":
            write(text(COMMAND, "QTM Version is mocapflow stand-in"))
        elif verb == "byteorder":
            write(text(COMMAND, "Byte order is little endian"))
        elif verb == "getstate":
            state = EVENT_RT_FROM_FILE_STOPPED if self.ended else (
                EVENT_RT_FROM_FILE_STARTED if self.started.is_set() else EVENT_CONNECTED)
            write(packet(EVENT, bytes([state])))
        elif verb == "getparameters":
            write(text(XML, parameters_xml(self.data)))
        elif verb in ("streamframes", "getcurrentframe"):
            self._stream(client, verb, [w.lower() for w in words[1:]])
        else:
            write(text(ERROR, f"{command.strip()}: not supported by this stand-in server"))

    def _stream(self, client: Client, verb: str, args: list[str]) -> None:
        if verb == "streamframes" and args[:1] == ["stop"]:
            client.divisor = 0
            return
        frames = args.pop(0) if verb == "streamframes" and args else "allframes"
        unknown = [a for a in args if a not in COMPONENTS]
        if unknown or not args:
            client.writer.write(text(ERROR, f"Parse error: component(s) {' '.join(unknown) or 'missing'} not served "
                                            "(this stand-in serves 3D and 3DNoLabels)"))
            return
        components = [COMPONENTS[a] for a in args]
        if verb == "getcurrentframe":
            client.writer.write(data_packet(self.current, components) if self.current else packet(NO_MORE_DATA, b""))
            return
        divisor = 1
        if frames.startswith("frequencydivisor:"):
            divisor = max(1, int(frames.split(":")[1]))
        elif frames.startswith("frequency:"):
            divisor = max(1, round(self.data.rate / float(frames.split(":")[1])))
        if self.ended:
            client.writer.write(packet(NO_MORE_DATA, b""))
            return
        client.components, client.divisor = components, divisor
        self.started.set()
