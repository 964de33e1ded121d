"""Key expressions: data on ``{prefix}/{node}/{output}``; runtime services under reserved ``_`` chunks
(docs/wire-format.md and docs/lab-deployment.md list them all)."""

from __future__ import annotations


def output_key(prefix: str, node: str, output: str) -> str:
    return f"{prefix}/{node}/{output}"


PREVIEW = "_preview"


def preview_key(prefix: str, node: str, output: str) -> str:
    """A thinned copy of a node's output stream, for viewers (``mocapflow.runtime.preview``)."""
    return f"{prefix}/{PREVIEW}/{node}/{output}"


def preview_of(key: str) -> str:
    """The preview key of output key ``{prefix}/{node}/{output}``."""
    prefix, node, output = key.rsplit("/", 2)
    return preview_key(prefix, node, output)


def is_preview(key: str) -> bool:
    return f"/{PREVIEW}/" in key


def unpreview(key: str) -> str:
    """The output key a preview key previews."""
    prefix, preview, node, output = key.rsplit("/", 3)
    if preview != PREVIEW:
        raise ValueError(f"{key!r} is not a preview key")
    return f"{prefix}/{node}/{output}"


def stats_key(prefix: str, node: str = "*") -> str:
    return f"{prefix}/_stats/{node}"


def alive_key(prefix: str, node: str = "*") -> str:
    return f"{prefix}/_alive/{node}"


def schema_key(prefix: str, type_name: str = "*") -> str:
    return f"{prefix}/_schema/{type_name}"


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
