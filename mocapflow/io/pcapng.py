"""UDP payloads from a packet capture (pcapng, Ethernet/IPv4), with their capture times: how a recorded tracker
session is read back to be replayed."""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

from mocapflow.errors import MocapflowError

SECTION, INTERFACE, ENHANCED = 0x0A0D0D0A, 1, 6
ETHERNET = 1


@dataclass(frozen=True)
class UdpPacket:
    time_s: float
    src_port: int
    dst_port: int
    payload: bytes


def read_udp(path: str | Path) -> list[UdpPacket]:
    """Every UDP datagram of a pcapng file, in capture order."""
    data = Path(path).read_bytes()
    if len(data) < 12 or struct.unpack_from("<I", data)[0] != SECTION:
        raise MocapflowError(f"{path}: not a pcapng capture")
    packets, resolution, at = [], 1e-6, 0
    while at + 12 <= len(data):
        kind, length = struct.unpack_from("<II", data, at)
        if length < 12 or at + length > len(data):
            raise MocapflowError(f"{path}: truncated block at byte {at}")
        if kind == INTERFACE:
            link = struct.unpack_from("<H", data, at + 8)[0]
            if link != ETHERNET:
                raise MocapflowError(f"{path}: link type {link} is not Ethernet")
            resolution = _resolution(data[at + 16:at + length - 4])
        elif kind == ENHANCED:
            high, low, captured = struct.unpack_from("<III", data, at + 12)
            frame = data[at + 28:at + 28 + captured]
            packet = _udp(frame, ((high << 32) | low) * resolution)
            if packet is not None:
                packets.append(packet)
        at += length
    return packets


def _resolution(options: bytes) -> float:
    at = 0
    while at + 4 <= len(options):
        code, size = struct.unpack_from("<HH", options, at)
        if code == 0:
            break
        if code == 9:  # if_tsresol
            value = options[at + 4]
            return 2.0 ** -(value & 0x7F) if value & 0x80 else 10.0 ** -value
        at += 4 + (size + 3) // 4 * 4
    return 1e-6


def _udp(frame: bytes, time_s: float) -> UdpPacket | None:
    if len(frame) < 42 or frame[12:14] != b"\x08\x00" or frame[23] != 17:  # IPv4, UDP
        return None
    ip_header = (frame[14] & 0x0F) * 4
    udp = 14 + ip_header
    src, dst, length = struct.unpack_from(">HHH", frame, udp)
    return UdpPacket(time_s, src, dst, frame[udp + 8:udp + length])
