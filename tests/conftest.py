"""Shared fixtures and helpers: free loopback endpoints for real Zenoh routers, the shared data folder, and the
command line run as a subprocess."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from collections.abc import Callable, Iterator
from itertools import repeat
from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

LOWEST_PORT = 10000
"""Test servers listen on this port or above: below it lie the well-known and most registered services' ports."""

CLI = [sys.executable, "-m", "mocapflow.cli"]
"""``mocapflow`` as a subprocess runs it."""


def run_cli(*args: str | Path, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """Run ``mocapflow ARGS`` to its end, its output captured as text (the caller checks the exit code)."""
    return subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=timeout, check=False)


def graph_file(folder: Path, stem: str, endpoint: str, nodes: str) -> tuple[Path, str]:
    """The graph file ``folder/stem.yaml`` of the YAML ``nodes`` (its lines under ``nodes:``), run with an embedded
    router on ``endpoint``; its name, and so its key prefix, is unique to the test. Returns the path and the prefix."""
    name = f"{stem}{endpoint.rsplit(':', 1)[1]}"
    path = folder / f"{stem}.yaml"
    path.write_text(f'name: {name}\nzenoh: {{listen: ["{endpoint}"]}}\nnodes:\n{nodes.strip(chr(10))}\n')
    return path, f"mocapflow/{name}"


def _port_block() -> Iterator[int]:
    """This test process's own ports, in turn: a block per pytest-xdist worker, below the range from which the system
    takes the local ports of outgoing connections. A port the system picks (bound to 0) is free only until some Zenoh
    session's connection takes it as its local port, which may happen before the server the test starts listens on
    it ("address already in use")."""
    try:
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        low = 0
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0)
    size = (low - LOWEST_PORT) // max(workers, 1)
    if size < 100:  # no room below that range: the system's own choice
        return repeat(0)
    return iter(range(LOWEST_PORT + worker * size, LOWEST_PORT + (worker + 1) * size))


_PORTS = _port_block()


def free_port() -> int:
    """A loopback TCP port free now, for a server that a test starts later (``_port_block``)."""
    for port in _PORTS:
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:  # in use, or still closing
                continue
            return s.getsockname()[1]
    raise RuntimeError("no free loopback port left in this test process's block")


@pytest.fixture
def free_endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not DATA.is_dir():
        pytest.skip(f"real data folder {DATA} is absent")
    return DATA


@pytest.fixture(scope="session")
def real_file() -> Callable[[str], Path]:
    """A file of the shared data folder by name; the test is skipped when it is absent."""

    def find(name: str) -> Path:
        path = DATA / name
        if not path.is_file():
            pytest.skip(f"real data file {path} is absent")
        return path

    return find
