"""``mocapflow run GRAPH`` and ``mocapflow validate GRAPH``."""

from __future__ import annotations

import argparse
from pathlib import Path

from mocapflow.commands import timeout_option
from mocapflow.runtime.graph import load_graph


def register(sub: argparse._SubParsersAction) -> None:
    run = sub.add_parser("run", help="run a graph: every node in its own supervised process")
    run.add_argument("graph", help="graph YAML file (see deployments/)")
    run.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    run.add_argument("--set", dest="overrides", action="append", default=[], metavar="NODE.KEY=VALUE",
                     help="override a node's config value (repeatable)")
    run.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                     help="endpoint of the embedded router (default tcp/127.0.0.1:7447)")
    run.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                     help="join an existing Zenoh router instead of starting one (needed for 'machine:' placements)")
    run.add_argument("--security", metavar="FILE", default=None,
                     help="security settings: TLS, login (docs/lab-deployment.md; default $MOCAPFLOW_SECURITY)")
    run.add_argument("--agent-timeout", type=float, default=30.0, metavar="S",
                     help="how long to wait for the agents of 'machine:' placements, at start or when one is lost")
    run.add_argument("--summary", metavar="FILE.json", default=None,
                     help="write each node's final state and statistics to a JSON file when the run ends")
    timeout_option(run)
    run.set_defaults(func=_run)

    val = sub.add_parser("validate", help="check a graph's plugins, ports, link types and configs")
    val.add_argument("graphs", nargs="+", help="graph YAML files")
    val.add_argument("--set", dest="overrides", action="append", default=[], metavar="NODE.KEY=VALUE")
    val.set_defaults(func=_validate)


def _run(args: argparse.Namespace) -> int:
    from mocapflow.runtime.graph import validate
    from mocapflow.runtime.launcher import Launcher

    graph = load_graph(args.graph, args.overrides)
    launcher = Launcher(graph, validate(graph), duration=args.duration, listen=args.listen, connect=args.connect,
                        security=args.security, agent_timeout=args.agent_timeout, summary=args.summary,
                        timeout=args.timeout)
    return launcher.run()


def _validate(args: argparse.Namespace) -> int:
    for path in args.graphs:
        graph = load_graph(Path(path), args.overrides)
        print(f"{path}: ok ({len(graph.nodes)} nodes: {', '.join(graph.nodes)})")
    return 0
