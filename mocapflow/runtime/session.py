"""Zenoh session configuration: one place decides modes, endpoints and scouting for every mocapflow process."""

from __future__ import annotations

import json
from collections.abc import Sequence

import zenoh

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


def zenoh_config(mode: str, *, listen: Sequence[str] = (), connect: Sequence[str] = ()) -> zenoh.Config:
    """A Zenoh config with multicast scouting and gossip off: a lab network is explicit, never discovered by chance.

    Timestamping is on so that model outputs can be cached for late joiners (Zenoh's advanced publisher needs it).
    """
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("scouting/gossip/enabled", "false")
    config.insert_json5("timestamping/enabled", "true")
    if listen:
        config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
        # Keep retrying: a router that restarts must not end a node.
        config.insert_json5("connect/timeout_ms", "-1")
    return config


def open_client(connect: Sequence[str]) -> zenoh.Session:
    """A client session to the given routers; used by nodes and by the CLI's introspection commands."""
    return zenoh.open(zenoh_config("client", connect=connect or [DEFAULT_ENDPOINT]))


def open_router(listen: Sequence[str]) -> zenoh.Session:
    """An embedded Zenoh router listening on ``listen``."""
    return zenoh.open(zenoh_config("router", listen=listen or [DEFAULT_ENDPOINT]))
