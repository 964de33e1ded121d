"""Progress on long offline work, printed to stderr so it never mixes with data on stdout."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import TypeVar

from mocapflow.mocap.report import steps

T = TypeVar("T")


class Reporter:
    """A ``mocap.report.Progress`` callback that writes ``label: done/total (pct) rate`` to stderr at most every
    ``every_s`` seconds. Reporting is skipped when stderr is not a terminal, unless ``enabled`` is forced by the
    caller, so logs stay clean."""

    def __init__(self, *, enabled: bool = True, every_s: float = 0.5) -> None:
        self.show = enabled and sys.stderr.isatty()
        self.every_s = every_s
        self.label = ""
        self.start = self.last = time.perf_counter()

    def __call__(self, label: str, done: int, total: int) -> None:
        if not self.show:
            return
        now = time.perf_counter()
        if label != self.label or done == 1:  # a new loop
            self.label, self.start, self.last = label, now, now - self.every_s
        if now - self.last >= self.every_s or done == total:
            self.last = now
            elapsed = now - self.start
            rate = f" {done / elapsed:,.0f}/s" if elapsed >= 0.1 else ""  # none yet on a loop's first step
            pct = 100.0 * done / total if total else 100.0
            sys.stderr.write(f"\r{label}: {done}/{total} ({pct:5.1f} %){rate}")
            if done == total:
                sys.stderr.write("\n")
            sys.stderr.flush()


def progress(items: Iterable[T], total: int, label: str, *, enabled: bool = True, every_s: float = 0.5) -> Iterator[T]:
    """Yield ``items`` unchanged while a ``Reporter`` shows how many are done."""
    return steps(items, total, label, Reporter(enabled=enabled, every_s=every_s))
