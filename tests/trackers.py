"""Helpers of the tracker tests: stand-in servers as real processes, and graphs run with ``mocapflow run``."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import yaml
from conftest import CLI


class Server:
    """``mocapflow serve PROTOCOL FILE --port PORT ...`` in its own process, ready once it has said so."""

    def __init__(self, protocol: str, path: Path | str, port: int, *args: str) -> None:
        self.process = subprocess.Popen([*CLI, "serve", protocol, str(path), "--port", str(port), *args],
                                        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert self.process.stdout is not None
        line = self.process.stdout.readline()
        assert "starts with the first client" in line, line + self.process.stdout.read()

    def stop(self) -> None:
        self.process.terminate()
        self.process.wait(timeout=30)

    def __enter__(self) -> Server:
        return self

    def __exit__(self, *_: object) -> None:
        self.stop()


def graph_file(tmp_path: Path, endpoint: str, tag: str, nodes: dict[str, Any]) -> Path:
    name = f"{tag}{endpoint.rsplit(':', 1)[1]}"
    path = tmp_path / f"{tag}.yaml"
    path.write_text(yaml.safe_dump({"name": name, "prefix": f"mocapflow/{name}", "zenoh": {"listen": [endpoint]},
                                    "nodes": nodes}, sort_keys=False))
    return path


def run_graph(graph: Path, *settings: str, timeout: float = 240) -> tuple[int, str, dict[str, Any]]:
    """Runs a graph to its end; its exit code, its output and its summary (node -> final statistics)."""
    summary = graph.with_suffix(".summary.json")
    done = subprocess.run([*CLI, "run", str(graph), "--duration", str(timeout - 60), "--summary", str(summary),
                           *(arg for s in settings for arg in ("--set", s))],
                          cwd=graph.parent, capture_output=True, text=True, timeout=timeout)
    stats = json.loads(summary.read_text()) if summary.exists() else {}
    return done.returncode, done.stdout + done.stderr, stats


def stream_graph(protocol: str, path: Path, port: int, graph: Path, receiver: str,
                 *server_args: str) -> tuple[int, str, dict[str, Any]]:
    """Serves ``path`` to ``graph`` once and runs the graph to its end, as ``run_graph``. NatNet streams frames over
    UDP, which a busy machine may drop: a session in which ``receiver`` (the first node after the tracker) counted a
    missing frame is played again, up to three sessions, so a comparison with the file is not spoilt by the network."""
    for _ in range(3 if protocol == "natnet" else 1):
        with Server(protocol, path, port, *server_args):
            code, out, stats = run_graph(graph)
        if code != 0 or stats.get(receiver, {}).get("drops", 0) == 0:
            break
    return code, out, stats
