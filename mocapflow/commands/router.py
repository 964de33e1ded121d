"""``mocapflow router [--listen ENDPOINT...] [--config FILE]``: the lab's Zenoh router, with TLS, users and access
control from a security settings file (docs/lab-deployment.md).

Without a settings file the router accepts anyone who reaches it, so it listens on loopback unless told otherwise,
and says loudly when it is told to listen on another address with no authentication."""

from __future__ import annotations

import argparse
import sys
import threading

from mocapflow.runtime.signals import stop_on_signals

PORT = 7447


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("router", help="run the lab's Zenoh router (TLS, users, access control)")
    parser.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                        help=f"endpoint to listen on (repeatable; default tcp/127.0.0.1:{PORT} without security "
                             f"settings, tcp/0.0.0.0:{PORT} with them, tls/0.0.0.0:{PORT} when they give the router "
                             "a certificate)")
    parser.add_argument("--config", metavar="FILE", default=None,
                        help="security settings: TLS certificate, users, access rules (default $MOCAPFLOW_SECURITY)")
    parser.set_defaults(func=run)


def loopback(endpoint: str) -> bool:
    """Whether an endpoint listens on this machine only."""
    host = endpoint.partition("/")[2].rsplit(":", 1)[0].strip("[]")
    return host in ("localhost", "::1") or host.startswith("127.")


def run(args: argparse.Namespace) -> int:
    import zenoh

    from mocapflow.runtime.session import open_router, settings

    chosen = settings(args.config)
    scheme = "tls" if chosen is not None and chosen.tls_listener else "tcp"
    host = "127.0.0.1" if chosen is None else "0.0.0.0"
    listen = args.listen or [f"{scheme}/{host}:{PORT}"]
    if (chosen is None or not chosen.accepted_users()) and any(not loopback(ep) for ep in listen):
        print(f"mocapflow router: WARNING: listening on {', '.join(ep for ep in listen if not loopback(ep))} with no "
              "authentication: anyone who reaches this address may read, publish, and deploy and stop nodes on "
              "every agent. Give the router users and access rules with --config (docs/lab-deployment.md).",
              file=sys.stderr, flush=True)
    stop = threading.Event()

    def on_transport(event: zenoh.TransportEvent) -> None:
        what = "joined" if event.kind == zenoh.SampleKind.PUT else "left"
        print(f"mocapflow router: {event.transport.whatami} {event.transport.zid} {what}", flush=True)

    with stop_on_signals(stop), open_router(listen, args.config) as session:
        security = "no security settings" if chosen is None else ", ".join([
            "TLS" if chosen.tls_listener else "no TLS",
            f"{len(chosen.accepted_users())} user(s)" if chosen.accepted_users() else "no authentication",
            "access control" if chosen.access is not None else "no access control",
        ])
        print(f"mocapflow router: {session.zid()} listening on {', '.join(listen)} ({security})", flush=True)
        with session.info.declare_transport_events_listener(on_transport):
            stop.wait()
    print("mocapflow router: stopped", flush=True)
    return 0
