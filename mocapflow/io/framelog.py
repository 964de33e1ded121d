"""An append-only log of wire messages: what a recorder writes as frames arrive, so a crash loses nothing before it.

A C3D or TRC file cannot be appended to (the header holds the frame count and the parameter section the labels,
which a labelled stream only learns as it goes), so the recorder streams each message as it arrives into
``OUT.part`` and converts it to ``OUT`` when the stream ends. The log is the plainest thing that survives a SIGKILL:
a header naming the run, then records ``[length u32][crc32 u32][port u8][wire JSON]``, each written with one
``write`` and flushed to the operating system. A record cut short by a crash fails its length or checksum and is
dropped when the log is opened again; a restarted recorder of the same run appends after the last whole record.
"""

from __future__ import annotations

import errno
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

from mocapflow.errors import MocapFileError

MAGIC = b"MFLOG1\n"
RECORD = struct.Struct("<IIB")
MAX_RECORD = 1 << 28


def part_path(path: str | Path) -> Path:
    """Where the log of an output file is written while its stream runs."""
    path = Path(path)
    return path.with_name(path.name + ".part")


def _read_header(stream: BinaryIO, path: Path) -> str:
    if stream.read(len(MAGIC)) != MAGIC:
        raise MocapFileError(f"{path}: not a mocapflow frame log")
    return stream.readline().decode(errors="replace").rstrip("\n")


def scan(path: str | Path) -> tuple[str, int, Iterator[tuple[int, bytes]]]:
    """(run, end of the last whole record, the records as (port, payload)) of a log; reading stops at the first
    damaged record."""
    path = Path(path)
    stream = path.open("rb")
    run = _read_header(stream, path)
    start = stream.tell()

    def records() -> Iterator[tuple[int, bytes]]:
        with stream:
            while True:
                head = stream.read(RECORD.size)
                if len(head) < RECORD.size:
                    return
                length, crc, port = RECORD.unpack(head)
                if length > MAX_RECORD:
                    return
                payload = stream.read(length)
                if len(payload) < length or zlib.crc32(payload, port) != crc:
                    return
                yield port, payload

    return run, start, records()


def whole_length(path: Path) -> int:
    """Bytes of the log up to the end of its last whole record."""
    run, end, records = scan(path)
    for _port, payload in records:
        end += RECORD.size + len(payload)
    return end


class FrameLog:
    """Appends records to ``path``; a log of the same run is continued, one of another run is moved aside."""

    def __init__(self, path: str | Path, run: str) -> None:
        self.path = Path(path)
        self.set_aside: Path | None = None
        try:
            self._open(run)
        except OSError as exc:
            raise MocapFileError(f"{self.path}: cannot record there: {exc.strerror or exc}") from None

    def _open(self, run: str) -> None:
        blocker = next((folder for folder in self.path.parents if folder.exists() and not folder.is_dir()), None)
        if blocker is not None:
            raise NotADirectoryError(errno.ENOTDIR, f"{blocker} is a file, not a folder")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists():
            try:
                previous, _, _ = scan(self.path)
            except MocapFileError:
                previous = "?"
            if previous != run:
                self.set_aside = self.path.with_name(f"{self.path.name}.{previous or 'earlier'}")
                self.path.rename(self.set_aside)
        self._stream: BinaryIO
        if self.path.exists():
            keep = whole_length(self.path)
            self._stream = self.path.open("r+b")
            self._stream.truncate(keep)  # only a record cut short by a crash is dropped
            self._stream.seek(keep)
            self.resumed = True
        else:
            self._stream = self.path.open("wb")
            self._stream.write(MAGIC + run.encode() + b"\n")
            self._stream.flush()
            self.resumed = False

    def append(self, port: int, payload: bytes) -> None:
        self._stream.write(RECORD.pack(len(payload), zlib.crc32(payload, port), port) + payload)
        self._stream.flush()

    def close(self) -> None:
        self._stream.close()
