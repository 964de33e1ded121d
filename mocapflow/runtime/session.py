"""Zenoh session configuration: one place decides modes, endpoints, scouting and security for every mocapflow process.

Security settings (TLS, login, users, access control; see ``mocapflow.runtime.security``) come from the file a
command was given, else from ``$MOCAPFLOW_SECURITY``, so that every session of a lab (router, agents, nodes, launcher,
introspection commands) applies the same file without passwords on any command line.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal

import zenoh
import zenoh.ext as zext

from mocapflow.errors import MocapflowError
from mocapflow.runtime.security import SecuritySettings, load_security, security_path

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
# Rejoin a restarted router within a second: agents and nodes keep their state and the stream resumes.
RECONNECT = {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}


def zenoh_config(mode: Literal["router", "client"], *, listen: Sequence[str] = (), connect: Sequence[str] = (),
                 security: SecuritySettings | None = None, users_file: Path | None = None,
                 timeout: float | None = None) -> zenoh.Config:
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
        # Keep retrying: a router that restarts must not end a node. A command a person typed gives up instead.
        config.insert_json5("connect/timeout_ms", "-1" if timeout is None else str(int(timeout * 1000)))
        config.insert_json5("connect/retry", json.dumps(RECONNECT))
    if security is not None:
        for key, value in security.zenoh_keys(mode, users_file).items():
            config.insert_json5(key, json.dumps(value))
    return config


MODELS_SEEN = 64
"""How many cached models a subscriber is sent at once from each publishing session. Zenoh counts them per session,
not per key: at 1, of a session's several cached outputs (a group's segments and skeleton, a model and its preview)
a late subscriber received one, or at random not all (9 times in 12 with three)."""


def model_history() -> zext.HistoryConfig:
    """What a subscriber asks of the publishers' caches: the latest value of every model output it matches, also of
    publishers that appear later."""
    return zext.HistoryConfig(detect_late_publishers=True, max_samples=MODELS_SEEN)


def subscribe_with_cache(session: zenoh.Session, key: str, callback: Callable[[zenoh.Sample], None]) -> Any:
    """A subscriber that also receives, at once, the cached latest value of every model output (segments,
    skeleton) matching ``key``, as nodes do; plain data keys arrive as with an ordinary subscriber."""
    return zext.declare_advanced_subscriber(session, key, callback, history=model_history())


def settings(security: str | Path | None = None) -> SecuritySettings | None:
    """The security settings a session applies: from ``security``, else ``$MOCAPFLOW_SECURITY``, else none."""
    path = security_path(security)
    return load_security(path) if path is not None else None


def open_client(connect: Sequence[str], security: str | Path | None = None,
                timeout: float | None = None) -> zenoh.Session:
    """A client session to the given routers; used by nodes, agents and the CLI's commands. Without ``timeout`` it
    waits for a router for ever (nodes outlive a router restart); with one, no router accepting this session within
    ``timeout`` seconds (none running, or a login it refuses) is a one-line error."""
    endpoints = list(connect) or [DEFAULT_ENDPOINT]
    config = zenoh_config("client", connect=endpoints, security=settings(security), timeout=timeout)
    try:
        return zenoh.open(config)
    except zenoh.ZError:
        if timeout is None:
            raise
        raise MocapflowError(f"no router accepted this session at {', '.join(endpoints)} within {timeout:g} s: is it "
                             "running there, and are the security settings (login, TLS) the router's? "
                             "(--timeout S to wait longer)") from None


def open_router(listen: Sequence[str], security: str | Path | None = None) -> zenoh.Session:
    """A Zenoh router listening on ``listen``: the lab's router, or the launcher's embedded one. An endpoint that is
    taken (another run or router on the same port) is a one-line error saying how to choose another."""
    chosen = settings(security)
    endpoints = list(listen) or [DEFAULT_ENDPOINT]
    try:
        if chosen is None:
            return zenoh.open(zenoh_config("router", listen=endpoints))
        with chosen.users_dictionary() as users_file:
            return zenoh.open(zenoh_config("router", listen=endpoints, security=chosen, users_file=users_file))
    except zenoh.ZError as exc:
        if "already in use" not in str(exc):
            raise
        raise MocapflowError(f"{', '.join(endpoints)}: address already in use (another mocapflow run or router?); "
                             "listen elsewhere with --listen tcp/127.0.0.1:PORT") from None
