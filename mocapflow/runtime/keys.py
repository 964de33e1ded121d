"""Key expressions: data on ``{prefix}/{node}/{output}``; runtime services under reserved ``_`` chunks
(docs/wire-format.md and docs/lab-deployment.md list them all)."""

from __future__ import annotations


def output_key(prefix: str, node: str, output: str) -> str:
    return f"{prefix}/{node}/{output}"


PREVIEW = "_preview"
"""Thinned copies of the data outputs, for viewers (``mocapflow.runtime.preview``)."""
SAMPLED = "_sampled"
"""Sampled copies of the data outputs, for model stages (``mocapflow.runtime.sampling``)."""
COPIES = (PREVIEW, SAMPLED)


def copy_key(prefix: str, kind: str, node: str, output: str) -> str:
    """A copy (``PREVIEW`` or ``SAMPLED``) of a node's output stream."""
    return f"{prefix}/{kind}/{node}/{output}"


def copy_of(key: str, kind: str) -> str:
    """The key of the ``kind`` copy of output key ``{prefix}/{node}/{output}``."""
    prefix, node, output = key.rsplit("/", 2)
    return copy_key(prefix, kind, node, output)


def copy_kind(key: str) -> str | None:
    """Which copy of an output stream ``key`` is (``PREVIEW`` or ``SAMPLED``); None for any other key."""
    parts = key.rsplit("/", 3)
    return parts[1] if len(parts) == 4 and parts[1] in COPIES else None


def original(key: str) -> str:
    """The output key that a copy's key copies."""
    prefix, kind, node, output = key.rsplit("/", 3)
    if kind not in COPIES:
        raise ValueError(f"{key!r} is not the key of a stream's copy")
    return f"{prefix}/{node}/{output}"


def stats_key(prefix: str, node: str = "*") -> str:
    return f"{prefix}/_stats/{node}"


def alive_key(prefix: str, node: str = "*") -> str:
    return f"{prefix}/_alive/{node}"


def schema_key(prefix: str, type_name: str = "*") -> str:
    return f"{prefix}/_schema/{type_name}"


def ended_key(prefix: str, node: str = "*") -> str:
    """The launcher's answer to which nodes of its run have finished, so their streams have ended."""
    return f"{prefix}/_ended/{node}"


AGENTS = "mocapflow/_agents"
CONTROL = "mocapflow-control"
"""Agents' control queryables (deploy, stop): a key space of their own, outside ``mocapflow/**``, so that an access
rule for read-only users of the data cannot reach them."""


def agent_key(name: str = "*") -> str:
    return f"{AGENTS}/{name}"


def deploy_key(name: str) -> str:
    return f"{CONTROL}/agents/{name}/deploy"


def stop_key(name: str) -> str:
    return f"{CONTROL}/agents/{name}/stop"


def procs_key(prefix: str, node: str = "*") -> str:
    return f"{prefix}/_procs/{node}"


def log_key(prefix: str, machine: str = "*") -> str:
    return f"{prefix}/_log/{machine}"


def launcher_key(prefix: str, run: str = "*") -> str:
    return f"{prefix}/_launcher/{run}"
