"""The node base class: what a plugin declares (ports, config) and the few calls it makes.

A node knows its inputs, its outputs, its config model and its algorithm object, nothing else: sessions, keys,
pacing, statistics and shutdown belong to the runtime (``mocapflow.runtime.worker``), so the same node class runs
under the launcher, under an agent on another machine, or in a test.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, Generic, TypeVar

from pydantic import BaseModel, ConfigDict

from mocapflow.messages import Message, MessageType
from mocapflow.runtime.inbox import QueuePolicy

RUN_ENV = "MOCAPFLOW_RUN"
"""The run a worker belongs to, set by the worker from its spec: a restarted node sees the same value."""

Publish = Callable[[str, Message], None]
"""How a node sends a message: ``publish(output_port, message)``."""


class NoConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")


ConfigT = TypeVar("ConfigT", bound=BaseModel)


@dataclass(frozen=True)
class Input:
    """An input port. ``state`` inputs carry models (segments, skeleton): a late joiner receives the latest one at
    once. A ``required`` input must be linked. A node finishes when every data input it is fed by (feedback loops
    aside, see ``graph.end_inputs``) has ended. ``queue`` is the port's inbox policy unless the graph sets one:
    ``latest`` for a sink that only ever shows the newest frame, ``preview`` for one that shows it at a display's
    rate (``mocapflow.runtime.preview``), ``sampled`` for a model stage that takes a sample of the frames by their
    number (``mocapflow.runtime.sampling``). An input of type ``NodeStats`` is linked to the
    nodes' health, ``_stats/*`` (every node) or ``_stats/NODE``, and must be a ``state`` input (it never ends)."""

    type: MessageType
    required: bool = True
    state: bool = False
    doc: str = ""
    queue: QueuePolicy = "all"


@dataclass(frozen=True)
class Output:
    """An output port. ``state`` outputs are cached so that nodes starting later receive the latest value."""

    type: type[Message]
    state: bool = False
    doc: str = ""


class Node(Generic[ConfigT]):
    """Base class of every stage.

    Subclasses set ``Config`` (a pydantic model; ``class MyNode(Node[MyConfig])`` types ``self.config`` as it),
    ``inputs`` and ``outputs``, build their algorithm objects in ``setup`` and implement ``process`` for each input
    message. A node with no inputs is a source: it sets ``rate`` in ``setup`` and implements ``emit``, which the
    runtime calls once per frame index at that rate, in order, starting from ``first_index``. The runtime validates
    the config once, against ``Config``, before it constructs the node; before the first message it sets ``linked``,
    the inputs the graph links, so that a node can leave to another stage what that stage is linked to give it.
    A node whose work runs compiled kernels names their loaders (``mocap.compiled``) in ``kernels``: they run before
    its setup, and the launcher runs those of its graph's nodes before it starts any, so that a machine compiles them
    once, not in every process at once, and no frame waits for them.
    """

    Config: ClassVar[type[BaseModel]] = NoConfig
    inputs: ClassVar[dict[str, Input]] = {}
    outputs: ClassVar[dict[str, Output]] = {}
    kernels: ClassVar[tuple[Callable[[], None], ...]] = ()

    rate: float = 0.0
    linked: frozenset[str] | None = None  # the input ports the graph links; None when driven outside a graph
    audience: Callable[[str], bool] | None = None  # set by the runtime: answers ``listened``
    clock_origin_ns: int | None = None  # sources: when frame 0 was due (wall clock), set by the runtime
    paced: ClassVar[bool] = True
    """Sources: False when frames are pushed by a device (a live tracker), so the runtime calls ``emit`` again at
    once instead of on the ``rate`` timetable, and ``emit`` itself waits for the next frame."""

    def __init__(self, config: ConfigT, publish: Publish, name: str = "node") -> None:
        self.config: ConfigT = config
        self.name = name
        self._publish = publish
        self.log = logging.getLogger(f"mocapflow.{name}")
        for load in self.kernels:
            load()
        self.setup()

    def setup(self) -> None:
        """Build the node's state from ``self.config``; called once, at the end of construction. Override this
        rather than ``__init__``."""

    @property
    def run_id(self) -> str:
        """Identifies the run (one launch of a graph): a node that keeps files can tell its own restart from a new
        run. Empty outside a launched graph."""
        return os.environ.get(RUN_ENV, "")

    @classmethod
    def is_source(cls) -> bool:
        return not cls.inputs

    def publish(self, output: str, message: Message) -> None:
        """Send ``message`` on one of this node's declared outputs."""
        self._publish(output, message)

    def listened(self, output: str) -> bool:
        """Whether a message published on ``output`` now would reach anyone: a node of the graph, or a subscriber
        such as a viewer or ``mocapflow echo`` (always, outside a graph). A node may leave out a costly message that
        nobody would read (the simulator's truth); what it publishes must not depend on it otherwise."""
        return self.audience is None or self.audience(output)

    def wanted(self, port: str) -> bool:
        """Whether the node will use the next message on data input ``port``. A stage that shows a stream at its own
        rate (a viewer) says no to the messages it would drop; the runtime then passes them over without
        decoding them or handing them over, and counts them as skipped. Asked once per message, in order, before
        ``process``; by default every message is wanted."""
        return True

    def process(self, port: str, message: Any) -> None:
        """Handle one message from input ``port``, of the type that input declares (so an override may name it).
        Exceptions are logged and counted; the stream goes on."""
        raise NotImplementedError(f"{type(self).__name__} declares inputs but does not implement process()")

    def process_batch(self, port: str, messages: list[Any]) -> None:
        """Handle several messages that queued up on one input while the node was busy, oldest first. Override it
        when a batch is cheaper than one call per message (vectorised work); by default the runtime calls
        ``process`` for each message instead, so a failing one costs only itself."""
        for message in messages:
            self.process(port, message)

    def emit(self, index: int) -> bool:
        """Sources: produce frame ``index``. Return False when the source has no more frames."""
        raise NotImplementedError(f"{type(self).__name__} is a source but does not implement emit()")

    def prepare(self, index: int) -> None:
        """Sources: the runtime calls it once the frame before ``index`` has been handled, before frame ``index`` is
        emitted (in the time left before it is due, or at once when the process is behind), so a paced source can
        work out ahead what its frames need, a step at a time (a simulator its next block of frames), instead of
        delaying one frame by all of it. It may come for the frame past the source's last (``emit`` then says there
        is none), and ``emit`` must not depend on it: by default nothing is done."""

    def due_ns(self, index: int) -> int:
        """Sources: when frame ``index`` is due on the runtime's timetable (wall clock, ns since the Unix epoch), the
        capture time of a simulated or replayed frame, so that latency also counts the time a frame was emitted late;
        the present moment outside a run."""
        if self.clock_origin_ns is None or not self.rate:
            return time.time_ns()
        return self.clock_origin_ns + round(index * 1e9 / self.rate)

    def first_index(self, elapsed_s: float) -> int:
        """Sources: the frame to start from, ``elapsed_s`` after frame 0 was due (0 on a first start). Resuming where
        the source's clock is after a restart, instead of at 0, keeps frame numbers increasing."""
        return max(0, int(elapsed_s * self.rate))

    def finish(self) -> None:
        """Called once when the node stops (end of its input streams, or a stop request): flush and release."""

    @classmethod
    def describe(cls) -> dict[str, Any]:
        """Ports and config schema, as shown by ``mocapflow plugins``."""
        return {
            "doc": " ".join((cls.__doc__ or "").strip().split("\n\n")[0].split()),
            "inputs": {
                k: {"type": v.type.type_name, "required": v.required, "state": v.state, "doc": v.doc}
                for k, v in cls.inputs.items()
            },
            "outputs": {k: {"type": v.type.type_name, "state": v.state, "doc": v.doc} for k, v in cls.outputs.items()},
            "config": cls.Config.model_json_schema(),
        }
