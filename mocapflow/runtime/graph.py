"""Graph files: which nodes run, with which plugin and config, linked how, on which machine.

Loading validates everything a run depends on before any process starts, and every error names the node and the
field (``nodes.filler.inputs.markers: ...``) so a broken graph is fixed from the message alone.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from mocapflow.errors import GraphError
from mocapflow.messages import NodeStats
from mocapflow.runtime.cpus import CpuPolicy
from mocapflow.runtime.inbox import DEFAULT_CAPACITY, QueuePolicy
from mocapflow.runtime.integrity import StreamLimits
from mocapflow.runtime.node import Input, Node
from mocapflow.runtime.plugins import PluginNotFound, load

NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]*$")
HEALTH = "_stats/"  # links to the nodes' health: the stats keys, ``keys.stats_key``, under the graph's prefix
KEY_PREFIX = re.compile(r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$")


class ZenohSettings(BaseModel):
    model_config = ConfigDict(extra="forbid")

    connect: list[str] = Field(default_factory=list, description="routers to join; empty: start an embedded router")
    listen: list[str] = Field(default_factory=list, description="endpoints of the embedded router")


Restart = Literal["on-failure", "never"]


class RestartPolicy(BaseModel):
    """What happens when a node's process ends with a failure (a configuration error is never retried): it starts
    again with backoff up to ``max_restarts`` times, or never. Declared per node in a graph, carried to the agent
    that runs it and applied by its supervisor."""

    restart: Restart = "on-failure"
    max_restarts: int = Field(default=5, ge=0)


class NodeSpec(RestartPolicy):
    model_config = ConfigDict(extra="forbid")

    plugin: str
    config: dict[str, Any] = Field(default_factory=dict)
    inputs: dict[str, str] = Field(default_factory=dict, description="input port -> 'node/output'")
    machine: str | None = Field(default=None, description="agent that runs this node; none: the launcher's machine")
    group: str | None = Field(default=None, description="node group: the nodes of a group run in one process and "
                              "hand messages to one another as Python objects (see docs/ARCHITECTURE.md)")
    nice: int = Field(default=0, ge=0, le=19, description="CPU niceness of the node's process (0 most favoured, "
                      "19 least): a model stage set at 10 yields the CPU to the frame path on a busy machine")
    cpu: CpuPolicy = Field(default="shared", description="'own': a CPU core of its own for the node's process (a "
                           "group's, if a member asks), no other process of the graph on that machine running there, "
                           "when the machine has a core to spare; 'shared': the cores left; 'idle': the cores left, "
                           "but only the CPU time no other process wants (a viewer: it never delays the pipeline, "
                           "and on a machine with no time to spare it draws nothing); 'realtime': the cores left, at "
                           "a real-time priority, ahead of every ordinary process (the frame path: a group's, if a "
                           "member asks and none asks 'own'; it needs root, CAP_SYS_NICE or an rtprio limit, and "
                           "without it runs as 'shared', with a warning)")
    queue: dict[str, QueuePolicy] = Field(
        default_factory=dict, description="input port -> 'all' (every message), 'latest' (the newest) or 'preview' "
        "(the newest of the output's preview, at most 60 a second: for viewers) or 'sampled' (every frame of the "
        "output's sampled copy, about 120 a second, frame numbers multiples of a stride: for model stages); "
        "default: the plugin's choice for that input, 'all' unless it says otherwise")
    queue_size: int = Field(default=DEFAULT_CAPACITY, ge=1,
                            description="messages the inbox holds at most; beyond, new ones are dropped and counted")
    wait_for: dict[str, float] = Field(
        default_factory=dict, description="input port -> ms: before a frame is handled, how long to wait for that "
        "input's message of the same frame number (the filler's prediction from another process); frames handled "
        "without it are counted")


class Graph(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str
    prefix: str | None = None
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    limits: StreamLimits = Field(default_factory=StreamLimits, description="what every node's data inputs accept")
    nodes: dict[str, NodeSpec]

    @field_validator("nodes")
    @classmethod
    def _names(cls, nodes: dict[str, NodeSpec]) -> dict[str, NodeSpec]:
        if not nodes:
            raise ValueError("a graph needs at least one node")
        for name in nodes:
            if not NAME.match(name):
                raise ValueError(f"node name {name!r} must be letters, digits, '-' or '_' and not start with '_'")
        return nodes

    @field_validator("name")
    @classmethod
    def _name(cls, name: str) -> str:
        if "/" in name or not KEY_PREFIX.match(name):
            raise ValueError(f"{name!r} must be letters, digits, '-', '_' or '.' (it names the graph's keys)")
        return name

    @field_validator("prefix")
    @classmethod
    def _prefix(cls, prefix: str | None) -> str | None:
        if prefix is not None and not KEY_PREFIX.match(prefix):
            raise ValueError(f"{prefix!r} must be '/'-separated chunks of letters, digits, '-', '_' or '.' (no empty "
                             "chunk, no wildcard)")
        return prefix

    @property
    def key_prefix(self) -> str:
        return self.prefix or f"mocapflow/{self.name}"

    def process_of(self, node: str) -> str:
        """The process a node runs in: its group, or the node alone."""
        return self.nodes[node].group or node

    def groups(self) -> dict[str, list[str]]:
        """Each node group and its members, in graph order."""
        groups: dict[str, list[str]] = {}
        for name, spec in self.nodes.items():
            if spec.group:
                groups.setdefault(spec.group, []).append(name)
        return groups

    def linked_outputs(self, node: str, classes: dict[str, type[Node]]) -> list[str]:
        """Outputs of ``node`` that a node in another process reads as they are (``classes``: each node's plugin). An
        input whose queue policy is 'sampled' or 'preview' reads the output's copy instead, which the node sends only
        while someone subscribes to it: linked that way, the output itself need not be sent."""
        return sorted({link.partition("/")[2] for name, spec in self.nodes.items() for port, link in spec.inputs.items()
                       if link.partition("/")[0] == node and self.process_of(name) != self.process_of(node)
                       and spec.queue.get(port, classes[name].inputs[port].queue) not in ("sampled", "preview")})


def _format_validation(exc: ValidationError, base: str = "") -> str:
    lines = []
    for err in exc.errors():
        where = ".".join(str(p) for p in (base, *err["loc"]) if p != "")
        lines.append(f"{where or 'graph'}: {err['msg']}")
    return "; ".join(lines)


def parse_override(text: str) -> tuple[str, str, Any]:
    """``node.key.sub=value`` -> (node, "key.sub", value); the value is read as YAML so numbers stay numbers."""
    lhs, sep, rhs = text.partition("=")
    node, dot, key = lhs.partition(".")
    if not sep or not dot or not node or not key:
        raise GraphError(f"--set {text!r}: expected NODE.KEY=VALUE")
    try:
        value = yaml.safe_load(rhs) if rhs else ""
    except yaml.YAMLError:
        value = rhs
    return node, key, value


def apply_overrides(raw: dict[str, Any], overrides: list[str]) -> None:
    nodes = raw.get("nodes") or {}
    for text in overrides:
        node, key, value = parse_override(text)
        if node not in nodes:
            raise GraphError(f"--set {text!r}: no node {node!r} in the graph (nodes: {', '.join(nodes)})")
        target = nodes[node].setdefault("config", {})
        *path, last = key.split(".")
        for depth, part in enumerate(path):
            target = target.setdefault(part, {})
            if not isinstance(target, dict):
                raise GraphError(f"--set {text!r}: {node}.{'.'.join(path[:depth + 1])} is a value, not a section")
        target[last] = value


def load_graph(path: str | Path, overrides: list[str] | None = None) -> Graph:
    """Read, override and fully validate a graph file."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise GraphError(f"{path}: cannot read: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise GraphError(f"{path}: not a text file (a graph is YAML)") from None
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}:{mark.column + 1}" if mark else str(path)
        problem = getattr(exc, "problem", None) or str(exc)
        raise GraphError(f"{where}: YAML syntax error: {problem}") from None
    if not isinstance(raw, dict):
        raise GraphError(f"{path}: a graph file must be a mapping with 'name' and 'nodes'")
    raw.setdefault("name", path.stem)
    apply_overrides(raw, overrides or [])
    try:
        graph = Graph.model_validate(raw)
    except ValidationError as exc:
        raise GraphError(f"{path}: {_format_validation(exc)}") from None
    validate(graph, str(path))
    return graph


def validate(graph: Graph, source: str = "graph") -> dict[str, type[Node]]:
    """Check plugins, configs, ports and link types; return each node's class. Collects every error."""
    errors: list[str] = []
    classes: dict[str, type[Node]] = {}
    for name, spec in graph.nodes.items():
        try:
            classes[name] = load(spec.plugin)
        except PluginNotFound as exc:
            errors.append(f"nodes.{name}.plugin: {exc}")
            continue
        try:
            classes[name].Config.model_validate(spec.config)
        except ValidationError as exc:
            errors.append(_format_validation(exc, f"nodes.{name}.config"))
    for name, spec in graph.nodes.items():
        cls = classes.get(name)
        if cls is None:
            continue
        for port, port_spec in cls.inputs.items():
            if port_spec.required and port not in spec.inputs:
                errors.append(f"nodes.{name}.inputs.{port}: required input is not linked ({port_spec.type.type_name})")
        for field, ports in (("queue", spec.queue), ("wait_for", spec.wait_for)):
            for port in ports:
                if port not in spec.inputs:
                    errors.append(f"nodes.{name}.{field}.{port}: no linked input {port!r} "
                                  f"(inputs: {', '.join(spec.inputs) or 'none'})")
                elif field == "wait_for" and (cls.inputs[port].state if port in cls.inputs else False):
                    errors.append(f"nodes.{name}.wait_for.{port}: {port!r} carries models, not frames")
        for port, bound in spec.wait_for.items():
            if bound <= 0:
                errors.append(f"nodes.{name}.wait_for.{port}: {bound} ms must be more than 0")
        for port, link in spec.inputs.items():
            where = f"nodes.{name}.inputs.{port}"
            if port not in cls.inputs:
                errors.append(f"{where}: plugin {spec.plugin!r} has no input {port!r} "
                              f"(inputs: {', '.join(cls.inputs) or 'none'})")
                continue
            if cls.inputs[port].type is NodeStats or link.startswith(HEALTH):
                errors += _health_errors(where, link, spec.plugin, cls.inputs[port], graph)
                continue
            src, slash, out = link.partition("/")
            if not slash or src not in graph.nodes:
                errors.append(f"{where}: {link!r} must be 'node/output' with a node of this graph")
                continue
            src_cls = classes.get(src)
            if src_cls is None:
                continue
            if out not in src_cls.outputs:
                errors.append(f"{where}: node {src!r} has no output {out!r} "
                              f"(outputs: {', '.join(src_cls.outputs) or 'none'})")
                continue
            want, have = cls.inputs[port].type, src_cls.outputs[out].type
            if want is not have:
                errors.append(
                    f"{where}: type mismatch: {link} carries {have.type_name}, input expects {want.type_name}")
    errors += _group_errors(graph, classes)
    if errors:
        raise GraphError(f"{source}: " + "; ".join(errors) if len(errors) == 1
                         else f"{source}:\n  " + "\n  ".join(errors))
    return classes


def _health_errors(where: str, link: str, plugin: str, port: Input, graph: Graph) -> list[str]:
    """An input of the nodes' health: of type NodeStats, a state input, linked to ``_stats/*`` or ``_stats/NODE``."""
    if port.type is not NodeStats:
        return [f"{where}: {link!r} carries NodeStats, input expects {port.type.type_name}"]
    if not port.state:
        return [f"{where}: plugin {plugin!r} takes node health on an input that is not a state input"]
    node = link.removeprefix(HEALTH)
    if not link.startswith(HEALTH) or (node != "*" and node not in graph.nodes):
        return [f"{where}: node health is linked as '{HEALTH}*' (every node) or '{HEALTH}NODE' with a node of this "
                f"graph, not {link!r}"]
    return []


def _group_errors(graph: Graph, classes: dict[str, type[Node]]) -> list[str]:
    errors = []
    for group, members in graph.groups().items():
        where = f"nodes.{members[0]}.group"
        if not NAME.match(group):
            errors.append(f"{where}: group name {group!r} must be letters, digits, '-' or '_'")
        elif group in graph.nodes and members != [group]:
            errors.append(f"{where}: group {group!r} has the name of another node: name it otherwise")
        placed = [m for m in members if graph.nodes[m].machine]
        if placed:
            errors.append(f"{where}: group {group!r} has nodes placed on machines ({', '.join(placed)}): a group runs "
                          "on the launcher's machine; leave placed nodes out of groups")
        sources = [m for m in members if m in classes and classes[m].is_source()]
        if len(sources) > 1:
            errors.append(f"{where}: group {group!r} has {len(sources)} sources ({', '.join(sources)}): one at most")
    return errors


def end_inputs(graph: Graph, classes: dict[str, type[Node]]) -> dict[str, list[str]]:
    """For each node, the data inputs whose end of stream it waits for before finishing.

    That is every linked data input, except feedback: an input whose source node is itself fed, directly or not, by
    this node (the labeller's predictions from the filler) ends only after this node has ended, so waiting for it
    would never finish. Waiting for the others (a recorder's poses, not only its markers) loses no tail frame.
    """
    feeds: dict[str, set[str]] = {name: set() for name in graph.nodes}
    for name, spec in graph.nodes.items():
        for link in spec.inputs.values():
            if not link.startswith(HEALTH):
                feeds[link.partition("/")[0]].add(name)

    def downstream(start: str) -> set[str]:
        seen, todo = set(), [start]
        while todo:
            for nxt in feeds[todo.pop()]:
                if nxt not in seen:
                    seen.add(nxt)
                    todo.append(nxt)
        return seen

    return {
        name: sorted(
            port for port, link in spec.inputs.items()
            if not classes[name].inputs[port].state and link.partition("/")[0] not in downstream(name)
        )
        for name, spec in graph.nodes.items()
    }
