"""Cores of their own: a node of a graph may ask for a CPU core that no other process of the graph on its machine
runs on (``cpu: own``), the frame path above all. On a machine with few cores the operating system otherwise moves
every process from core to core as they wake, and a frame's Python work, its caches cold each time, costs about half
as much again (docs/ARCHITECTURE.md, Speed)."""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Literal

ONE_THREAD = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
"""Set to 1 (unless set already) for node processes and benchmarks: their numerical work is on small arrays, where a
BLAS library's worker threads only spin; at 1000 Hz they took the frame group from 0.8 to 1.03 cores. Only effective
before numpy loads: this module imports nothing that loads it."""

CpuPolicy = Literal["shared", "own", "idle", "realtime"]
"""``shared``: the cores no process asked for; ``own``: a core of its own; ``idle``: the shared cores, but only the
CPU time nothing else wants (Linux's SCHED_IDLE), so that a sink such as a viewer never delays the pipeline;
``realtime``: the shared cores, at a real-time priority (Linux's SCHED_FIFO at ``REALTIME_PRIORITY``): the process
runs as soon as it is ready, ahead of every ordinary process, so that the frame path is not kept waiting while the
model stages solve. It needs the right to (root, CAP_SYS_NICE or an ``rtprio`` limit); without it the process runs
as ``shared`` and says so."""

REALTIME_PRIORITY = 10
"""SCHED_FIFO priority of a ``cpu: realtime`` process: low among real-time priorities (1-99), so that the kernel's
most urgent threads still come first; any real-time priority comes before every ordinary process."""


def assign_cores(own: Mapping[str, bool],
                 cores: set[int] | None = None) -> tuple[dict[str, list[int]], list[int]] | None:
    """The cores each process runs on, given which ask for one of their own (``own``: process name -> asks), and the
    cores left for the others (the launcher or agent itself among them). Each process that asks gets one core, the
    highest-numbered first; ``cores`` are those this process may use (default: its own affinity). None when no process
    asks, or when too few cores are left: one at least must remain for the others."""
    owners = [name for name, asks in own.items() if asks]
    available = sorted(os.sched_getaffinity(0) if cores is None else cores)
    if not owners or len(available) <= len(owners):
        return None
    shared = available[:len(available) - len(owners)]
    placed = {name: [core] for name, core in zip(owners, reversed(available), strict=False)}
    return {name: placed.get(name, shared) for name in own}, shared
