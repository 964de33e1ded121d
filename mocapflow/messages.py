"""Typed messages and their wire codec.

Every message is a pydantic model. On the wire it is one UTF-8 JSON object (see docs/wire-format.md):
numpy arrays travel as flat JSON arrays of numbers in row-major order, with ``null`` for a missing value (NaN),
and the message type is declared in Zenoh's encoding field as ``application/json;mocapflow/<Type>``. Any language
with a Zenoh client and a JSON parser can read and write them; each type's JSON Schema is served on
``{prefix}/_schema/<Type>``.

orjson encodes numpy arrays natively (NaN becomes null), which keeps a 60-marker frame at a few microseconds.
"""

from __future__ import annotations

from functools import cache
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal, Self, TypeAlias

import numpy as np
import orjson
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PlainSerializer,
    SerializationInfo,
    ValidationError,
    WithJsonSchema,
    model_validator,
)
from pydantic.functional_validators import BeforeValidator

from mocapflow.mocap.flags import CASE_OBSERVED
from mocapflow.mocap.model import Segment, SkeletonModel

SCHEMA_PREFIX = "mocapflow/"


class DecodeError(ValueError):
    """A payload that is not a valid message of the expected type."""


def _flat(array: np.ndarray, info: SerializationInfo) -> Any:
    """Flat row-major values: the array itself for orjson (fast path), a list for pydantic's own JSON."""
    flat = np.ascontiguousarray(array).ravel()
    return flat if info.mode == "python" else flat.tolist()


def _array(dtype: type, width: int | None) -> Any:
    """An ndarray field: accepts an array or a (flat or nested) list, stores ``(n, width)`` or ``(n,)`` of ``dtype``."""

    def validate(value: Any) -> np.ndarray:
        try:
            arr: np.ndarray = np.asarray(value, dtype=dtype)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"not an array of {np.dtype(dtype).name}: {exc}") from None
        if width is None:
            if arr.ndim != 1:
                raise ValueError(f"expected a flat array, got shape {arr.shape}")
            return arr
        if arr.ndim == 1:
            if arr.size % width:
                raise ValueError(f"flat array of {arr.size} values is not a multiple of {width}")
            arr = arr.reshape(-1, width)
        if arr.ndim != 2 or arr.shape[1] != width:
            raise ValueError(f"expected shape (n, {width}), got {arr.shape}")
        return arr

    item: dict[str, Any] = {"type": "number"} if np.dtype(dtype).kind == "f" else {"type": "integer"}
    if np.dtype(dtype).kind == "f":
        item = {"anyOf": [item, {"type": "null"}]}
    doc = f"flat row-major array, {width} values per row" if width else "flat array"
    return Annotated[
        np.ndarray,
        BeforeValidator(validate),
        PlainSerializer(_flat),
        WithJsonSchema({"type": "array", "items": item, "description": doc + "; null = missing"}),
    ]


if TYPE_CHECKING:  # to a type checker the fields are plain arrays
    Points: TypeAlias = np.ndarray
    Rays: TypeAlias = np.ndarray
    Quaternions: TypeAlias = np.ndarray
    Flags: TypeAlias = np.ndarray
    Indices: TypeAlias = np.ndarray
else:
    Points = _array(np.float32, 3)
    Rays = _array(np.float32, 6)
    Quaternions = _array(np.float64, 4)
    Flags = _array(np.uint8, None)
    Indices = _array(np.int32, None)


class Message(BaseModel):
    """Fields every message carries: the tracker frame it derives from and that frame's capture time."""

    model_config = ConfigDict(arbitrary_types_allowed=True, extra="forbid")
    type_name: ClassVar[str]

    frame: int = Field(ge=0, description="tracker frame number")
    capture_ns: int = Field(description="capture time of that frame on the tracker's clock, ns since the Unix epoch")

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls.type_name = cls.__name__

    @classmethod
    def encoding(cls) -> str:
        return f"application/json;{SCHEMA_PREFIX}{cls.type_name}"

    @classmethod
    def derive(cls, source: Message, **fields: Any) -> Self:
        """A message of this type about the same tracker frame as ``source``: its frame number, capture time and
        (where both types have one) rate carried over, ``fields`` giving the rest (or overriding them)."""
        carried = {name: getattr(source, name) for name in _carried(cls, type(source))}
        return cls(**{**carried, **fields})


@cache
def _carried(target: type[Message], source: type[Message]) -> tuple[str, ...]:
    """The fields ``derive`` carries from a ``source`` message to a ``target`` one (looked up once per pair of types:
    derive runs several times a frame)."""
    return tuple(name for name in ("frame", "capture_ns", "rate")
                 if name in target.model_fields and name in source.model_fields)


class MarkerFrame(Message):
    """One frame of markers. Labelled streams keep row order fixed; unlabelled streams have no labels."""

    rate: float = Field(gt=0, description="tracker frame rate, Hz")
    positions: Points = Field(description="N x 3 positions in mm, null = missing")
    labels: list[str] | None = Field(default=None, description="N labels; absent for an unlabelled point cloud")
    flags: Flags | None = Field(default=None, description="N per-marker flags: 0 missing, 1 observed, >= 2 estimated")
    rays: Rays | None = Field(
        default=None, description="N x 6 single-camera rays (origin mm, unit direction), null rows where none"
    )

    @model_validator(mode="after")
    def _same_length(self) -> MarkerFrame:
        n = len(self.positions)
        for name in ("labels", "flags", "rays"):
            value = getattr(self, name)
            if value is not None and len(value) != n:
                raise ValueError(f"{name} has {len(value)} entries for {n} markers")
        return self

    def observed(self) -> np.ndarray:
        """(N, 3) positions of the observed samples only, NaN where a sample is missing or was estimated (filled
        markers: flags other than 1): what a stage that learns a model from the data may use."""
        if self.flags is None:
            return self.positions
        return np.where((self.flags == CASE_OBSERVED)[:, None], self.positions, np.nan)


class Segments(Message):
    """The current segment model: which markers move together."""

    segments: list[Segment]


class Skeleton(Message):
    """The current skeleton model."""

    skeleton: SkeletonModel


class Pose(Message):
    """A solved skeleton pose: joint centres and segment rotations for one frame."""

    joint_names: list[str]
    joint_centres: Points = Field(description="J x 3 joint centres in mm, null = unknown")
    segment_names: list[str]
    rotations: Quaternions = Field(description="S x 4 segment rotations as quaternions (x, y, z, w)")
    translations: Points = Field(description="S x 3 segment origins in mm")


class SimTruth(Message):
    """Ground truth of a simulated frame, for evaluation."""

    labels: list[str] = Field(description="N marker labels, in the simulator's marker order")
    identity: Indices = Field(description="for each published point row: the true marker index, -1 for a ghost")
    true_positions: Points = Field(description="N x 3 noise-free marker positions")
    joint_names: list[str]
    joint_centres: Points = Field(description="J x 3 true joint centres")


class NodeStats(BaseModel):
    """Health and throughput of one node, published periodically on ``{prefix}/_stats/{node}``."""

    model_config = ConfigDict(extra="forbid")
    type_name: ClassVar[str] = "NodeStats"

    node: str
    pid: int
    state: Literal["starting", "running", "finished", "stopping", "failed"] = Field(
        description="'failed': its finish() failed at the end of its stream, so what it was to write is lost")
    frames_in: int = 0
    frames_out: int = 0
    rate_hz: float = 0.0
    latency_p50_ms: float | None = Field(default=None, description=(
        "from the tracker's capture timestamp to the frame handled (ms): over the latest 4096 frames while the node "
        "runs, over its whole run once it has ended (to within 1 %)"))
    latency_p99_ms: float | None = Field(default=None, description="as latency_p50_ms, the 99th percentile")
    drops: int = Field(default=0, description="frames lost: missing frame numbers, or refused by a full inbox")
    skipped: int = Field(default=0, description="messages passed over: for a newer one ('queue: latest' inputs), or "
                         "not wanted (a model stage sampling its input)")
    backlog: int = Field(default=0, description="messages waiting in the inbox now")
    backlog_ms: float = Field(default=0.0, description="how long the oldest waiting message has waited (ms)")
    backlog_max: int = Field(default=0, description="most messages waiting at once during the run")
    backlog_max_ms: float = Field(default=0.0, description="longest any message waited during the run (ms)")
    errors: int = 0
    refused: int = Field(default=0, description="input samples refused (wrong publisher, frame number, size)")
    unpaired: int = Field(default=0, description="frames handled without the input they wait for ('wait_for')")
    last_error: str | None = None
    clock_origin_ns: int | None = Field(default=None, description="sources: wall-clock time of frame 0")

    @classmethod
    def encoding(cls) -> str:
        return f"application/json;{SCHEMA_PREFIX}{cls.type_name}"


MessageType = type[Message] | type[NodeStats]
"""A type that travels on the wire: a message, or a node's statistics."""

MESSAGE_TYPES: dict[str, MessageType] = {
    t.type_name: t for t in (MarkerFrame, Segments, Skeleton, Pose, SimTruth, NodeStats)
}


_FLAT_TYPES: frozenset[type[BaseModel]] = frozenset((MarkerFrame, Pose, SimTruth))
"""Message types whose fields are numbers, strings, lists of strings and arrays: their wire form is their fields with
each array flattened, which ``encode`` writes without pydantic's serialiser (half the cost of a frame's encode)."""


def encode(message: BaseModel) -> bytes:
    """Serialise a message to its JSON wire form."""
    if type(message) in _FLAT_TYPES:
        data = {name: np.ascontiguousarray(value).ravel() if isinstance(value, np.ndarray) else value
                for name, value in message.__dict__.items()}
    else:
        data = message.model_dump(mode="python")
    return orjson.dumps(data, option=orjson.OPT_SERIALIZE_NUMPY)


def decode(payload: bytes | bytearray | memoryview, message_type: MessageType) -> Any:
    """Parse and validate a payload as ``message_type``; raise DecodeError with a one-line reason otherwise."""
    try:
        data = orjson.loads(payload)
    except orjson.JSONDecodeError as exc:
        raise DecodeError(f"not JSON: {exc}") from None
    if not isinstance(data, dict):
        raise DecodeError(f"expected a JSON object for {message_type.type_name}, got {type(data).__name__}")
    try:
        return message_type.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "message"
        raise DecodeError(
            f"invalid {message_type.type_name}: {where}: {first['msg']} ({exc.error_count()} error(s))"
        ) from None


def json_schema(message_type: MessageType) -> dict[str, Any]:
    """The JSON Schema of a message type, as served to clients in other languages."""
    schema = message_type.model_json_schema(mode="serialization")
    schema["$id"] = f"{SCHEMA_PREFIX}{message_type.type_name}"
    return schema
