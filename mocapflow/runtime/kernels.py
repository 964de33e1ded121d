"""The numeric kernels made ready before a launcher or an agent starts nodes, or an offline command starts its work
(``mocap.compiled``)."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, TimeoutError
from typing import IO


def compile_kernels(out: IO[str], *stages: Callable[[], None]) -> None:
    """Compile the numeric kernels of ``stages`` (``mocap.compiled``'s loaders), or load them from numba's cache,
    before the work starts, so that it finds them ready; say so when it takes long (the first run on a machine)."""

    def load() -> None:
        for stage in stages:
            stage()

    with ThreadPoolExecutor(1) as pool:
        done = pool.submit(load)
        try:
            done.result(timeout=2.0)
        except TimeoutError:
            out.write("mocapflow: compiling the numeric kernels for this machine (once; about half a minute)\n")
            out.flush()
            done.result()
