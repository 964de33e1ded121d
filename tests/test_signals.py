"""Stop signals, however many and however they interleave, end a process in order and never hang it.

A handler that sets a threading.Event deadlocks when a second signal lands while the first handler holds the
event's lock; a worker orphaned by a killed agent can get SIGTERM from the kernel and from a supervisor at once.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

CHILD = textwrap.dedent("""
    import signal, threading, time
    from mocapflow.runtime.signals import stop_on_signals
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # as a worker: once the block is left, stop requests are ignored
    stop = threading.Event()
    seen = []
    with stop_on_signals(stop, on_signal=seen.append):
        print("ready", flush=True)
        stop.wait()
        time.sleep(1.0)  # still under the handler while the signals keep coming
    print("stopped by", seen[0].name, len(seen) > 1, flush=True)
""")


@pytest.mark.integration
def test_a_stream_of_sigterm_stops_the_process_once_and_never_hangs_it() -> None:
    child = subprocess.Popen([sys.executable, "-c", CHILD], stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout is not None
        assert child.stdout.readline().strip() == "ready"
        end = time.monotonic() + 1.5
        while child.poll() is None and time.monotonic() < end:
            os.kill(child.pid, signal.SIGTERM)
            time.sleep(0.0002)
        out, _ = child.communicate(timeout=30)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert child.returncode == 0
    assert out.strip() == "stopped by SIGTERM True"


ELSEWHERE = textwrap.dedent("""
    import signal, threading, time
    from mocapflow.runtime.signals import stop_on_signals
    stop = threading.Event()

    def elsewhere():
        time.sleep(0.5)  # the main thread is waiting by now
        signal.pthread_kill(threading.get_ident(), signal.SIGTERM)

    with stop_on_signals(stop):
        # the kernel may hand a process's signal to any of its threads (a Zenoh session runs several): here, to one
        # that is not the main thread, which waits without a timeout and is never woken to run a Python handler
        threading.Thread(target=elsewhere).start()
        stop.wait()
    print("stopped", flush=True)
""")


@pytest.mark.integration
def test_a_signal_landing_on_another_thread_stops_a_main_thread_waiting_without_timeout() -> None:
    done = subprocess.run([sys.executable, "-c", ELSEWHERE], capture_output=True, text=True, timeout=30)
    assert (done.returncode, done.stdout.strip()) == (0, "stopped"), done.stderr
