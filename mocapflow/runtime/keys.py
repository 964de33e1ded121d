"""Key expressions: data on ``{prefix}/{node}/{output}``; runtime services under reserved ``_`` chunks."""

from __future__ import annotations


def output_key(prefix: str, node: str, output: str) -> str:
    return f"{prefix}/{node}/{output}"


def stats_key(prefix: str, node: str = "*") -> str:
    return f"{prefix}/_stats/{node}"


def alive_key(prefix: str, node: str = "*") -> str:
    return f"{prefix}/_alive/{node}"


def schema_key(prefix: str, type_name: str = "*") -> str:
    return f"{prefix}/_schema/{type_name}"
