"""Stop requests by signal, safe however many signals arrive, whenever and on whichever thread they arrive.

A Python signal handler runs in the main thread between two bytecodes. A handler that sets a ``threading.Event``
deadlocks when a second signal lands while the main thread, or the first handler, holds the event's lock (a worker
orphaned by a killed agent gets SIGTERM from the kernel and from its supervisor at once). And the kernel may deliver
a process's signal to any of its threads (Zenoh's among them): the main thread, waiting without a timeout, is then
never woken to run a Python handler at all. So the Python handler here does nothing; the interpreter's C-level
handler writes the signal's number to a pipe (``signal.set_wakeup_fd``) on whichever thread the signal lands, taking
no lock, and a thread of its own reads it and sets the event.
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _noted(_signum: int, _frame: FrameType | None) -> None:
    """The Python-level handler: the signal was already written to the wakeup pipe."""


@contextmanager
def stop_on_signals(stop: threading.Event, signals: tuple[signal.Signals, ...] = STOP_SIGNALS,
                    on_signal: Callable[[signal.Signals], None] | None = None) -> Iterator[None]:
    """Within the block, set ``stop`` (after calling ``on_signal`` with the signal, from another thread) when any of
    ``signals`` arrives; the previous handlers and wakeup pipe are restored on leaving. Call from the main thread."""
    read, write = os.pipe()
    os.set_blocking(write, False)
    wanted = {int(s) for s in signals}

    def relay() -> None:
        while data := os.read(read, 64):
            for number in data:
                if number in wanted:  # the pipe also hears signals other handlers take (SIGINT's default)
                    if on_signal is not None:
                        on_signal(signal.Signals(number))
                    stop.set()
        os.close(read)

    thread = threading.Thread(target=relay, name="signals", daemon=True)
    thread.start()
    previous = {s: signal.signal(s, _noted) for s in signals}
    previous_fd = signal.set_wakeup_fd(write, warn_on_full_buffer=False)
    try:
        yield
    finally:
        signal.set_wakeup_fd(previous_fd)
        for s, old in previous.items():
            signal.signal(s, old)
        os.close(write)  # ends the relay once it has passed on what is in the pipe
        thread.join()
