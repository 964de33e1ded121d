"""Shared fixtures: free loopback endpoints for real Zenoh routers, and the shared data folder."""

from __future__ import annotations

import socket
from collections.abc import Callable
from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def free_endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def data_dir() -> Path:
    if not DATA.is_dir():
        pytest.skip(f"real data folder {DATA} is absent")
    return DATA


@pytest.fixture
def real_file() -> Callable[[str], Path]:
    """A file of the shared data folder by name; the test is skipped when it is absent."""

    def find(name: str) -> Path:
        path = DATA / name
        if not path.is_file():
            pytest.skip(f"real data file {path} is absent")
        return path

    return find
