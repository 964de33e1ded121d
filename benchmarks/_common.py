"""What the benchmarks share: BLAS pinned to one thread, the shared data folder, and CPU timing.

Import it before numpy (``import _common`` sorts first among the third-party imports): the thread settings only
take effect if they are set before numpy loads BLAS. With one thread, CPU seconds measure the work itself, so a busy
machine does not inflate them. Benchmarks run as scripts (``python benchmarks/NAME.py``), which puts this folder on
the import path.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mocapflow.runtime.cpus import ONE_THREAD  # loads no numpy

for _var in ONE_THREAD:
    os.environ.setdefault(_var, "1")

ROOT = Path(__file__).resolve().parents[1]
"""The project folder."""
DATA = ROOT.parent / "shared" / "data"
"""The shared folder of real captures (absent on most machines: every benchmark skips what it cannot find)."""


def timed(fn: Callable[..., Any], *args: object, **kwargs: object) -> tuple[Any, float]:
    """The result of ``fn`` and the CPU seconds it took."""
    start = time.process_time()
    out = fn(*args, **kwargs)
    return out, time.process_time() - start
