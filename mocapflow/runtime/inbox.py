"""A node's inbox: what arrived on its inputs and waits to be handled, in arrival order, with a stated policy per input.

``all`` (the default) keeps every message, up to ``capacity`` waiting at once; beyond that a new message is refused
and counted in ``drops``. ``latest`` keeps at most one waiting message per input: a newer one replaces it where it
waits, and each replaced one is counted in ``skipped`` (a viewer shows the newest frame rather than fall behind).
``preview`` is ``latest`` on a thinned copy of the stream (``mocapflow.runtime.preview``): the inbox holds it as
``latest``, the worker subscribes to the preview. ``sampled`` is ``all`` on the stream's sampled copy
(``mocapflow.runtime.sampling``), for model stages. End of stream is never refused or replaced. ``backlog`` says how
far behind the node is: messages waiting and how long the oldest has waited. Transport-free: it holds whatever the
caller puts in (a Zenoh sample, a message).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Generic, Literal, TypeVar

T = TypeVar("T")

QueuePolicy = Literal["all", "latest", "preview", "sampled"]
DEFAULT_CAPACITY = 100_000


@dataclass
class Entry(Generic[T]):
    port: str
    item: T
    end: bool
    arrived: float
    skipped: int = 0
    """How many messages of its input were passed over just before this one: replaced by it while it waited
    (``latest``) or refused by a full inbox (``all``), so that a gap in frame numbers is not counted twice."""


class Inbox(Generic[T]):
    def __init__(self, capacity: int = DEFAULT_CAPACITY, latest: set[str] | frozenset[str] = frozenset()) -> None:
        self.capacity = capacity
        self.latest = set(latest)
        self.drops: dict[str, int] = {}
        self.skipped: dict[str, int] = {}
        self.max_backlog: dict[str, tuple[int, float]] = {}  # per input: most waiting, longest wait (ms) when taken
        self._entries: deque[Entry[T]] = deque()
        self._waiting: dict[str, Entry[T]] = {}  # latest inputs: the one message of each that waits
        self._refused: dict[str, int] = {}  # per input, refused since its last queued message
        self._lock = threading.Condition()

    def put(self, port: str, item: T, end: bool = False) -> bool:
        """Queue ``item`` from input ``port`` (``end``: its end of stream); False if it was refused (counted)."""
        now = time.monotonic()
        with self._lock:
            if not end and port in self.latest:
                waiting = self._waiting.get(port)
                if waiting is not None:
                    waiting.item, waiting.skipped = item, waiting.skipped + 1
                    self.skipped[port] = self.skipped.get(port, 0) + 1
                    return True
                entry = self._waiting[port] = Entry(port, item, end, now)
            elif not end and len(self._entries) >= self.capacity:
                self.drops[port] = self.drops.get(port, 0) + 1
                self._refused[port] = self._refused.get(port, 0) + 1
                return False
            else:
                entry = Entry(port, item, end, now, self._refused.pop(port, 0))
            self._entries.append(entry)
            self._lock.notify()
        return True

    def get(self, timeout: float | None = None) -> Entry[T] | None:
        """The oldest waiting entry, waiting up to ``timeout`` s for one (0: do not wait); None if there is none."""
        with self._lock:
            if not self._entries and (timeout == 0 or not self._lock.wait(timeout)):
                return None
            if not self._entries:
                return None
            entry = self._entries.popleft()
            if not entry.end and entry.port in self.latest:
                del self._waiting[entry.port]
            waited = (time.monotonic() - entry.arrived) * 1e3
            most, longest = self.max_backlog.get(entry.port, (0, 0.0))
            self.max_backlog[entry.port] = max(most, len(self._entries) + 1), max(longest, waited)
            return entry

    def backlog(self) -> tuple[int, float]:
        """Messages waiting now, and how long the oldest of them has waited (ms)."""
        with self._lock:
            if not self._entries:
                return 0, 0.0
            return len(self._entries), (time.monotonic() - self._entries[0].arrived) * 1e3

    def figures(self, ports: set[str]) -> dict[str, int | float]:
        """What a node's statistics say of its inputs ``ports``: refused (``drops``), ``skipped``, the backlog now
        (of the whole inbox: the node waits behind all of it) and the largest seen on these inputs."""
        backlog, backlog_ms = self.backlog()
        return {
            "drops": sum(self.drops.get(p, 0) for p in ports), "skipped": sum(self.skipped.get(p, 0) for p in ports),
            "backlog": backlog, "backlog_ms": round(backlog_ms, 3),
            "backlog_max": max((self.max_backlog[p][0] for p in ports if p in self.max_backlog), default=0),
            "backlog_max_ms": round(max((self.max_backlog[p][1] for p in ports if p in self.max_backlog),
                                        default=0.0), 3),
        }
