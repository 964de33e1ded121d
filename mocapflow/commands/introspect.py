"""Looking at a running system: ``plugins``, ``nodes``, ``echo``, ``hz`` and ``schema``."""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from typing import Any

import numpy as np
import orjson
import zenoh

from mocapflow.commands import timeout_option
from mocapflow.messages import MESSAGE_TYPES, json_schema
from mocapflow.runtime import keys
from mocapflow.runtime.plugins import available, load
from mocapflow.runtime.session import DEFAULT_ENDPOINT, open_client, subscribe_with_cache


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("plugins", help="list installed plugins with their ports (and config schema with -v)")
    p.add_argument("name", nargs="?", help="show one plugin in full")
    p.set_defaults(func=_plugins)

    def with_connect(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                            help=f"router to join (default {DEFAULT_ENDPOINT})")
        timeout_option(parser)

    n = sub.add_parser("nodes", help="list live nodes and their health")
    n.add_argument("--prefix", default="mocapflow/**", help="key prefix of the run (default: every run)")
    with_connect(n)
    n.set_defaults(func=_nodes)

    e = sub.add_parser("echo", help="print messages on a key as readable text")
    e.add_argument("key", help="key expression, e.g. mocapflow/quickstart/tracker/markers")
    e.add_argument("-n", "--count", type=int, default=None, help="stop after N messages")
    e.add_argument("--full", action="store_true", help="print whole arrays instead of a summary")
    with_connect(e)
    e.set_defaults(func=_echo)

    h = sub.add_parser("hz", help="measure the message rate on a key")
    h.add_argument("key")
    h.add_argument("--window", type=float, default=2.0, help="seconds per report")
    h.add_argument("-n", "--reports", type=int, default=None, help="stop after N reports")
    with_connect(h)
    h.set_defaults(func=_hz)

    s = sub.add_parser("schema", help="print the JSON Schema of a message type")
    s.add_argument("type", choices=sorted(MESSAGE_TYPES))
    s.set_defaults(func=_schema)


def _plugins(args: argparse.Namespace) -> int:
    names = [args.name] if args.name else sorted(available())
    for name in names:
        info = load(name).describe()
        ports = lambda d: ", ".join(  # noqa: E731
            f"{k}: {v['type']}" + ("" if v.get("required", True) else "?") for k, v in d.items()) or "-"
        print(f"{name}: {info['doc']}\n  inputs:  {ports(info['inputs'])}\n  outputs: {ports(info['outputs'])}")
        props = info["config"].get("properties", {})
        required = set(info["config"].get("required", []))
        for key, prop in props.items():
            default = "required" if key in required else f"default {json.dumps(prop.get('default'))}"
            desc = prop.get("description", "")
            print(f"    config.{key}: {prop.get('type', prop.get('anyOf', '') and 'any')} ({default}) {desc}".rstrip())
    return 0


def _nodes(args: argparse.Namespace) -> int:
    prefix = args.prefix.rstrip("/")
    stats: dict[str, dict] = {}
    with open_client(args.connect, timeout=args.timeout) as session:
        alive = sorted(str(r.ok.key_expr) for r in session.liveliness().get(keys.alive_key(prefix), timeout=2.0)
                       if r.ok is not None)

        def on_stats(sample: zenoh.Sample) -> None:
            stats[str(sample.key_expr).replace("/_stats/", "/_alive/")] = orjson.loads(sample.payload.to_bytes())

        with session.declare_subscriber(keys.stats_key(prefix), on_stats):
            time.sleep(1.2)
    if not alive:
        print("no live nodes")
        return 1

    def backlog(s: dict[str, Any]) -> str:
        return f"{s['backlog']}/{s['backlog_ms']:.0f}ms" if "backlog" in s else "-"
    print(f"{'NODE':<44}{'STATE':<10}{'PID':>8}{'RATE Hz':>10}{'P50 ms':>8}{'P99 ms':>8}{'DROPS':>7}{'SKIP':>7}"
          f"{'BACKLOG':>12}{'ERR':>5}")
    for key in alive:
        s = stats.get(key, {})
        fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
        name = key.replace("/_alive/", "/")
        print(f"{name:<44}{s.get('state', '?'):<10}{s.get('pid', '-'):>8}{fmt(s.get('rate_hz')):>10}"
              f"{fmt(s.get('latency_p50_ms')):>8}{fmt(s.get('latency_p99_ms')):>8}"
              f"{s.get('drops', 0):>7}{s.get('skipped', 0):>7}{backlog(s):>12}{s.get('errors', 0):>5}")
    return 0


def _summary(value: object, full: bool) -> object:
    """Long numeric arrays shortened to their size, missing count and first values; everything else as is."""
    if full or not isinstance(value, list) or len(value) <= 12:
        return value
    if not all(v is None or isinstance(v, (int, float)) for v in value):
        return f"[{len(value)} items: {', '.join(map(str, value[:6]))}, ...]"
    arr = np.array([np.nan if v is None else v for v in value], dtype=float)
    return f"[{len(value)} values, {int(np.isnan(arr).sum())} missing, first {arr[:6].round(2).tolist()}...]"


def _echo(args: argparse.Namespace) -> int:
    done = threading.Event()
    count = 0

    def on_sample(sample: zenoh.Sample) -> None:
        nonlocal count
        if done.is_set():
            return
        head = f"{sample.key_expr} [{sample.encoding}]"
        if sample.kind == zenoh.SampleKind.DELETE:
            text = "(end of stream)"
        else:
            payload = sample.payload.to_bytes()
            try:
                data = orjson.loads(payload)
                if isinstance(data, dict):
                    text = "\n".join(f"  {k}: {_summary(v, args.full)}" for k, v in data.items())
                else:
                    text = f"  {data}"
            except orjson.JSONDecodeError:
                text = f"  ({len(payload)} bytes, not JSON)"
        print(f"{head}\n{text}", flush=True)
        count += 1
        if args.count is not None and count >= args.count:
            done.set()

    with open_client(args.connect, timeout=args.timeout) as session, \
            subscribe_with_cache(session, args.key, on_sample):
        try:
            while not done.wait(0.2):
                pass
        except KeyboardInterrupt:
            pass
    return 0


def _hz(args: argparse.Namespace) -> int:
    stamps: list[float] = []
    lock = threading.Lock()

    def on_sample(_sample: zenoh.Sample) -> None:
        with lock:
            stamps.append(time.perf_counter())

    reports = 0
    with open_client(args.connect, timeout=args.timeout) as session, session.declare_subscriber(args.key, on_sample):
        try:
            while args.reports is None or reports < args.reports:
                time.sleep(args.window)
                with lock:
                    window, stamps[:] = list(stamps), []
                reports += 1
                if len(window) < 2:
                    print(f"{args.key}: no messages", flush=True)
                    continue
                gaps = np.diff(window)
                print(f"{args.key}: {len(window) / args.window:.1f} Hz  (interval mean {gaps.mean() * 1e3:.3f} ms,"
                      f" sd {gaps.std() * 1e3:.3f} ms, max {gaps.max() * 1e3:.3f} ms, n={len(window)})", flush=True)
        except KeyboardInterrupt:
            pass
    return 0


def _schema(args: argparse.Namespace) -> int:
    json.dump(json_schema(MESSAGE_TYPES[args.type]), sys.stdout, indent=2)
    print()
    return 0
