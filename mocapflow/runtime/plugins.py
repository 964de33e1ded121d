"""Finding plugins: installed packages register node classes under the ``mocapflow.plugins`` entry-point group;
a graph may also name a class directly as ``module:Class`` for quick experiments."""

from __future__ import annotations

import importlib
from functools import cache
from importlib.metadata import entry_points

from mocapflow.errors import MocapflowError
from mocapflow.runtime.node import Node

ENTRY_POINT_GROUP = "mocapflow.plugins"


class PluginNotFound(MocapflowError, LookupError):
    """No installed plugin has that name, or its class cannot be loaded."""


@cache
def available() -> dict[str, str]:
    """Registered plugin names and the ``module:Class`` each refers to."""
    return {ep.name: ep.value for ep in entry_points(group=ENTRY_POINT_GROUP)}


def load(name: str) -> type[Node]:
    """Resolve a plugin name or ``module:Class`` path to its node class."""
    target = available().get(name, name)
    if ":" not in target:
        known = ", ".join(sorted(available())) or "none"
        raise PluginNotFound(f"unknown plugin {name!r} (installed: {known}; or give module:Class)")
    module_name, _, attr = target.partition(":")
    try:
        cls = getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError) as exc:
        raise PluginNotFound(f"cannot load plugin {name!r} from {target!r}: {exc}") from None
    if not (isinstance(cls, type) and issubclass(cls, Node)):
        raise PluginNotFound(f"plugin {name!r} ({target}) is not a mocapflow Node class")
    return cls
