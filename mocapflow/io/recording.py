"""Recordings of Zenoh traffic as MCAP files.

MCAP is the robotics community's standard log container: indexed, seekable, streamable while being written, and
opened by Foxglove Studio, the ``mcap`` CLI and readers in C++, Go, Python, Rust, Swift and TypeScript. Each key is a
channel whose messages are JSON (``message_encoding: json``) with the message type's JSON Schema attached
(``schema encoding: jsonschema``), so another tool can decode a recording with no knowledge of mocapflow.
Log time is when the sample was received; end-of-stream (a Zenoh DELETE) is kept on a companion channel marked
``zenoh_kind: delete``. The writer flushes every chunk it completes, so a recording whose writer was killed keeps
everything up to its last chunk: ``read_recording`` reads such a file front to back, up to where it was cut.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import orjson
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from mocapflow.errors import MocapFileError
from mocapflow.messages import MESSAGE_TYPES, SCHEMA_PREFIX, json_schema

PROFILE = "mocapflow"
CHUNK_SIZE = 64 * 1024


@dataclass(frozen=True)
class RecordedSample:
    key: str
    encoding: str
    payload: bytes
    log_time_ns: int
    delete: bool = False


class RecordingWriter:
    """Append samples to an MCAP file; one channel per (key, encoding, kind)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._stream = self.path.open("wb")
        except OSError as exc:
            raise MocapFileError(f"{self.path}: cannot write a recording there: {exc.strerror}") from None
        self._writer = Writer(self._stream, compression=CompressionType.ZSTD, chunk_size=CHUNK_SIZE)
        self._writer.start(profile=PROFILE, library="mocapflow")
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str, bool], int] = {}
        self._sequence = 0
        self.count = 0

    def _schema_id(self, encoding: str) -> int:
        type_name = encoding.partition(f";{SCHEMA_PREFIX}")[2]
        if type_name not in MESSAGE_TYPES:
            return 0
        if type_name not in self._schemas:
            self._schemas[type_name] = self._writer.register_schema(
                name=f"{SCHEMA_PREFIX}{type_name}", encoding="jsonschema",
                data=orjson.dumps(json_schema(MESSAGE_TYPES[type_name])),
            )
        return self._schemas[type_name]

    def write(self, sample: RecordedSample) -> None:
        ident = (sample.key, sample.encoding, sample.delete)
        if ident not in self._channels:
            schema = self._schema_id(sample.encoding)
            self._channels[ident] = self._writer.register_channel(
                topic=sample.key,
                message_encoding="json" if sample.encoding.startswith("application/json") else sample.encoding,
                schema_id=schema,
                metadata={"zenoh_encoding": sample.encoding, "zenoh_kind": "delete" if sample.delete else "put"},
            )
        self._sequence += 1
        self._writer.add_message(self._channels[ident], log_time=sample.log_time_ns, data=sample.payload,
                                 publish_time=sample.log_time_ns, sequence=self._sequence)
        self.count += 1

    def flush(self) -> None:
        """Hand what is written (every completed chunk) to the operating system: a killed writer keeps it."""
        self._stream.flush()

    def close(self) -> None:
        self._writer.finish()
        self._stream.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_recording(path: str | Path) -> Iterator[RecordedSample]:
    """Samples of a recording in log-time order."""
    path = Path(path)
    if not path.is_file():
        raise MocapFileError(f"{path}: no such file")
    with path.open("rb") as stream:
        if stream.read(8) != b"\x89MCAP0\r\n":
            raise MocapFileError(f"{path}: not an MCAP recording")
        stream.seek(0)
        try:
            reader = make_reader(stream)
            reader.get_summary()
        except (McapError, EOFError, ValueError, struct.error):
            yield from _read_cut(stream)  # no summary: its writer stopped before closing it
            return
        try:
            for _schema, channel, message in reader.iter_messages(log_time_order=True):
                yield _sample(channel, message)
        except (McapError, EOFError, ValueError) as exc:
            raise MocapFileError(f"{path}: damaged MCAP recording: {exc}") from None


def _sample(channel: Channel, message: Message) -> RecordedSample:
    return RecordedSample(
        key=channel.topic, encoding=channel.metadata.get("zenoh_encoding", channel.message_encoding),
        payload=message.data, log_time_ns=message.log_time, delete=channel.metadata.get("zenoh_kind") == "delete",
    )


def _read_cut(stream: BinaryIO) -> Iterator[RecordedSample]:
    """The messages of a recording cut short, in the order written, up to the first incomplete record."""
    stream.seek(0)
    channels: dict[int, Channel] = {}
    try:
        for record in StreamReader(stream, skip_magic=False).records:
            if isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message) and record.channel_id in channels:
                yield _sample(channels[record.channel_id], record)
    except (McapError, EOFError, ValueError, struct.error):
        return
