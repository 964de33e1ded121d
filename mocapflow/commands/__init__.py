"""Subcommands of the mocapflow CLI: each module defines ``register(subparsers)``."""

from __future__ import annotations

from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from mocapflow.errors import MocapflowError

M = TypeVar("M", bound=BaseModel)


def settings(model: type[M], items: list[str], **named: Any) -> M:
    """A config model from ``--set KEY=VALUE`` options (values read as YAML, so numbers stay numbers) and named
    options (None = not given); a bad value is a one-line error naming the setting."""
    import yaml

    values: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise MocapflowError(f"--set {item!r}: expected KEY=VALUE")
        values[key.strip()] = yaml.safe_load(value)
    values.update({key: value for key, value in named.items() if value is not None})
    try:
        return model.model_validate(values)
    except ValidationError as exc:
        raise MocapflowError("; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())) from None
