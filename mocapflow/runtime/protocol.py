"""The vocabulary launchers and agents speak over Zenoh (docs/lab-deployment.md): what a launcher asks an agent to
run (``Deployment`` of ``Placement``s), what an agent answers about its nodes (``ProcStatus``), and the error either
side reports."""

from __future__ import annotations

from collections.abc import Mapping

import zenoh
from pydantic import BaseModel, Field

from mocapflow.errors import MocapflowError
from mocapflow.messages import DecodeError, NodeStats, decode
from mocapflow.runtime.graph import RestartPolicy
from mocapflow.runtime.worker import WorkerSpec


class AgentError(MocapflowError):
    """Agents needed by a graph are missing, refuse a deployment, or were lost for good."""


class Placement(RestartPolicy):
    """One node an agent is asked to run, with the restart policy its supervisor applies."""

    spec: WorkerSpec
    source: bool


class Deployment(BaseModel):
    """The nodes of one run that a launcher places on one agent."""

    run: str = Field(description="id of the launcher's run; its liveliness token is {prefix}/_launcher/{run}")
    prefix: str
    nodes: list[Placement]


class ProcStatus(BaseModel):
    """What an agent knows of one of its nodes: the supervisor's view, not the node's own statistics."""

    run: str
    node: str
    machine: str
    state: str
    pid: int | None = None
    restarts: int = 0
    exit_code: int | None = None


def keep_clock_origin(specs: Mapping[str, WorkerSpec], sample: zenoh.Sample) -> NodeStats | None:
    """Decode a node's statistics and remember a source's clock origin in its spec, so that a restart, here or on
    another agent, resumes on the source's clock with increasing frame numbers."""
    try:
        stats = decode(sample.payload.to_bytes(), NodeStats)
    except DecodeError:
        return None
    spec = specs.get(stats.node)
    if spec is not None and stats.clock_origin_ns is not None:
        spec.clock_origin_ns = stats.clock_origin_ns
    return stats
