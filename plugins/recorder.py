"""Recorder sink: writes a marker stream (and solved joint centres, when linked) to a C3D or TRC file."""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, field_validator

from mocapflow.io.framelog import FrameLog, part_path
from mocapflow.io.recorded import PORTS, convert_log
from mocapflow.messages import MarkerFrame, Pose, encode
from mocapflow.runtime.node import Input, Node


class RecorderConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    path: str = Field(description="output file; .c3d or .trc")

    @field_validator("path")
    @classmethod
    def _suffix(cls, path: str) -> str:
        if Path(path).suffix.lower() not in (".c3d", ".trc"):
            raise ValueError(f"{path!r}: the recorder writes .c3d or .trc files")
        return path


class Recorder(Node[RecorderConfig]):
    """Writes every received frame at its frame number; frames that never arrived are left missing (NaN). Joint
    centres become one extra point per joint name ever received (the skeleton may change during a run), missing in
    frames whose pose lacks that joint.

    Frames go to ``PATH.part`` as they arrive (``mocapflow.io.framelog``): a killed recorder loses nothing it had
    received, and its restart appends to the same log. When the stream ends the log becomes ``PATH``, the first
    copy of each frame number kept; the log is removed once ``PATH`` is written."""

    Config = RecorderConfig
    inputs = {
        "markers": Input(MarkerFrame, doc="markers to record"),
        "pose": Input(Pose, required=False, doc="solved poses: joint centres are written as extra points"),
    }

    def setup(self) -> None:
        self.log_file = FrameLog(part_path(self.config.path), self.run_id)  # fails at start on a path it cannot write
        if self.log_file.set_aside is not None:
            self.log.warning("an unfinished recording of another run is kept as %s", self.log_file.set_aside)
        if self.log_file.resumed:
            self.log.info("resuming %s after a restart", self.log_file.path)

    def process(self, port: str, message: MarkerFrame | Pose) -> None:
        self.log_file.append(PORTS[port], encode(message))

    def finish(self) -> None:
        self.log_file.close()
        written = convert_log(self.log_file.path, Path(self.config.path), self.log)
        if written:
            self.log_file.path.unlink()
