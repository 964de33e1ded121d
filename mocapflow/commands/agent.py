"""``mocapflow agent --name NAME --connect ENDPOINT``: run the nodes that graphs place on this machine."""

from __future__ import annotations

import argparse

from mocapflow.commands import timeout_option
from mocapflow.errors import MocapflowError
from mocapflow.runtime.graph import NAME
from mocapflow.runtime.session import DEFAULT_ENDPOINT


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("agent", help="run the nodes that graphs place on this machine (machine: NAME)")
    parser.add_argument("--name", required=True, help="this machine's name, as graphs write it in 'machine:'")
    parser.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                        help=f"the lab's router (default {DEFAULT_ENDPOINT})")
    parser.add_argument("--security", metavar="FILE", default=None,
                        help="security settings: TLS, login (docs/lab-deployment.md; default $MOCAPFLOW_SECURITY)")
    timeout_option(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from mocapflow.runtime.agent import run_agent
    from mocapflow.runtime.security import security_path

    if not NAME.match(args.name):
        raise MocapflowError(f"--name {args.name!r}: a machine name is letters, digits, '-' or '_'")
    return run_agent(args.name, args.connect or [DEFAULT_ENDPOINT], security_path(args.security), args.timeout)
