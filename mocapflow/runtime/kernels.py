"""The numeric kernels made ready before a launcher or an agent starts nodes (``mocap.compiled``)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor, TimeoutError
from typing import IO

from mocapflow.mocap.compiled import compile_all


def compile_kernels(out: IO[str]) -> None:
    """Compile the numeric kernels (``mocap.compiled``), or load them from numba's cache, before any node starts, so
    that the nodes all find them ready; say so when it takes long (the first run on a machine)."""
    with ThreadPoolExecutor(1) as pool:
        done = pool.submit(compile_all)
        try:
            done.result(timeout=2.0)
        except TimeoutError:
            out.write("mocapflow: compiling the numeric kernels for this machine (once; about half a minute)\n")
            out.flush()
            done.result()
