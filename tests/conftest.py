"""Shared fixtures and helpers: free loopback endpoints for real Zenoh routers, the shared data folder, and the
command line run as a subprocess."""

from __future__ import annotations

import socket
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

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


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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
