"""Progress on long offline work, printed to stderr so it never mixes with data on stdout."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")


def progress(items: Iterable[T], total: int, label: str, *, enabled: bool = True, every_s: float = 0.5) -> Iterator[T]:
    """Yield ``items`` unchanged while reporting ``label: done/total (pct) rate`` at most every ``every_s`` seconds.

    Reporting is skipped when stderr is not a terminal, unless ``enabled`` is forced by the caller, so logs stay clean.
    """
    show = enabled and sys.stderr.isatty()
    start = last = time.perf_counter()
    done = 0
    for item in items:
        yield item
        done += 1
        now = time.perf_counter()
        if show and (now - last >= every_s or done == total):
            last = now
            rate = done / max(now - start, 1e-9)
            pct = 100.0 * done / total if total else 100.0
            sys.stderr.write(f"\r{label}: {done}/{total} ({pct:5.1f} %) {rate:,.0f}/s")
            if done == total:
                sys.stderr.write("\n")
            sys.stderr.flush()
