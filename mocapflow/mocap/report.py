"""How long computations report progress: through a callback their caller supplies, so the algorithms print
nothing (the commands pass one that draws on the terminal, ``mocapflow.progress.Reporter``)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")

Progress = Callable[[str, int, int], None]
"""``progress(label, done, total)``: called after each step of a long loop."""


def steps(items: Iterable[T], total: int, label: str, progress: Progress | None) -> Iterator[T]:
    """Yield ``items`` unchanged, telling ``progress`` (when given) after each one how many are done."""
    for done, item in enumerate(items, start=1):
        yield item
        if progress is not None:
            progress(label, done, total)
