"""Stop requests by signal, safe however many signals arrive and whenever they arrive.

A Python signal handler runs in the main thread between two bytecodes. A handler that sets a ``threading.Event``
deadlocks when a second signal lands while the main thread, or the first handler, holds the event's lock (a worker
orphaned by a killed agent gets SIGTERM from the kernel and from its supervisor at once). The handler here only
writes the signal's number to a pipe, which takes no lock; a thread of its own reads it and sets the event.
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextmanager
def stop_on_signals(stop: threading.Event, signals: tuple[signal.Signals, ...] = STOP_SIGNALS,
                    on_signal: Callable[[signal.Signals], None] | None = None) -> Iterator[None]:
    """Within the block, set ``stop`` (after calling ``on_signal`` with the signal, from another thread) when any of
    ``signals`` arrives; the previous handlers are restored on leaving. Call from the main thread."""
    read, write = os.pipe()
    os.set_blocking(write, False)

    def handler(signum: int, _frame: FrameType | None) -> None:
        try:
            os.write(write, bytes([signum]))
        except BlockingIOError:  # the pipe is full: stop requests are already on their way
            pass

    def relay() -> None:
        while data := os.read(read, 64):
            if on_signal is not None:
                on_signal(signal.Signals(data[0]))
            stop.set()
        os.close(read)

    thread = threading.Thread(target=relay, name="signals", daemon=True)
    thread.start()
    previous = {s: signal.signal(s, handler) for s in signals}
    try:
        yield
    finally:
        for s, old in previous.items():
            signal.signal(s, old)
        os.close(write)  # ends the relay once it has passed on what is in the pipe
        thread.join()
