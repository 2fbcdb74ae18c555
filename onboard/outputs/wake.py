"""A wake-up signal from the tracking loop to an output's thread that never
makes the loop wait, and can wait itself until the loop is done with a frame.

A `threading.Condition` needs its lock on both sides: when the woken thread
holds it (between its wake-up and its next wait), the loop's `notify()` waits
for it too. A bare lock used as a binary semaphore has no such side: `set()`
releases it (never blocks; a signal already pending stays one), `wait()`
acquires it with a timeout, consuming the signal; a `set()` before the
`wait()` leaves the lock free, so no wake-up is lost.

Waking a thread still costs the waker: the kernel may run the woken thread
at once on the loop's core, and it then wants the interpreter lock the loop
holds. Measured in `nislam run` on a loaded 2-core machine, the loop's
publish stage took p95 12 ms, p99 26 ms with the wake-ups and 0.1 / 1 ms
without. So the service defers them (`deferred = True`): `set()` only notes
the signal, and the loop calls `flush()` once the frame is finished, right
before it waits for the next one. Threads other than the loop, and closing,
use `set_now()`.
"""

from __future__ import annotations

import threading


class Wake:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._lock.acquire()  # held: no signal pending
        self.deferred = False  # set by the service loop (see the module docstring)
        self._pending = False

    def set(self) -> None:
        """Signal the waiting thread (never blocks); deferred: at `flush()`."""
        if self.deferred:
            self._pending = True
        else:
            self.set_now()

    def set_now(self) -> None:
        try:
            self._lock.release()
        except RuntimeError:  # already free: a signal is pending
            pass

    def flush(self) -> None:
        """Deliver a deferred signal (the loop, once its frame is done)."""
        if self._pending:
            self._pending = False
            self.set_now()

    def wait(self, timeout_s: float | None) -> bool:
        """Wait for a signal up to `timeout_s` (None: for ever); True if one came."""
        if timeout_s is None:
            return self._lock.acquire()
        return self._lock.acquire(timeout=max(0.0, timeout_s))


def defer_wakeups(outputs: object) -> list[Wake]:
    """The wake-ups of `outputs` (an OutputGroup or one output), switched to
    deferred: the caller flushes them once per loop turn."""
    wakes: list[Wake] = []
    for out in getattr(outputs, "outputs", (outputs,)):
        for w in getattr(out, "wakeups", lambda: ())():
            w.deferred = True
            wakes.append(w)
    return wakes
