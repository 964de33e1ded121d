"""The marker-set contract of labelled streams: the set of markers only grows.

A labeller publishes its confirmed markers in a fixed order and appends each marker it confirms; it never drops or
reorders one. Every stage fed labelled markers meets this: on a frame whose labels extend the ones it knows, it takes
on the new markers and keeps all it holds about the others (filters, models, statistics, frames); only labels that
do not extend its own (another marker set) start it afresh.
"""

from __future__ import annotations

from collections.abc import Sequence


def added(known: Sequence[str], labels: Sequence[str]) -> list[str] | None:
    """The labels appended to ``known`` in ``labels`` (empty when they are the same); None when ``labels`` does not
    extend ``known``."""
    if len(labels) < len(known) or list(labels[: len(known)]) != list(known):
        return None
    return list(labels[len(known):])
