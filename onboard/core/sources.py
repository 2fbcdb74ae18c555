"""What every driver thread shares: start/stop on an Event, join with a
timeout, reconnect backoff, and counters a test (or a status page) can wait on.

A driver's `_run()` owns its device: it opens, reads, parses, timestamps and
hands over the newest sample, and reconnects by itself. Locks are held only to
swap a value or bump a counter, never across a device read. `stop()` sets the
stop Event, calls `_interrupt()` (cancel a pending read where the transport
can) and joins with a timeout, so shutdown never hangs on a dead device.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from types import TracebackType
from typing import Any, Generic, TypeVar

log = logging.getLogger(__name__)

DEFAULT_STOP_TIMEOUT_S = 5.0

S = TypeVar("S")


class Counters(Generic[S]):
    """A dataclass of counters behind a Condition: drivers bump fields after a
    read (never while reading), readers take a snapshot or wait for a predicate."""

    def __init__(self, initial: S) -> None:
        self._value = initial
        self._cond = threading.Condition()

    def bump(self, **deltas: int) -> None:
        with self._cond:
            self._value = dataclasses.replace(
                self._value, **{k: getattr(self._value, k) + d for k, d in deltas.items()}
            )
            self._cond.notify_all()

    def set(self, **values: Any) -> None:
        with self._cond:
            self._value = dataclasses.replace(self._value, **values)
            self._cond.notify_all()

    def snapshot(self) -> S:
        with self._cond:
            return self._value

    def wait_for(self, predicate: Callable[[S], bool], timeout_s: float) -> bool:
        """Block until `predicate(snapshot)` holds or `timeout_s` passes."""
        with self._cond:
            return self._cond.wait_for(lambda: predicate(self._value), timeout_s)


class Backoff:
    """Reconnect delays: `min_s`, doubling up to `max_s`; `reset()` after a
    connection delivered data."""

    def __init__(self, min_s: float, max_s: float) -> None:
        self.min_s = float(min_s)
        self.max_s = max(float(max_s), self.min_s)
        self._next = self.min_s

    def next(self) -> float:
        delay = self._next
        self._next = min(self._next * 2.0, self.max_s)
        return delay

    def reset(self) -> None:
        self._next = self.min_s


class DriverThread:
    """A daemon thread running `_run()` until `stop()`; a context manager."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.last_stop_s: float | None = None  # how long the last stop() took

    # -- lifecycle

    def start(self) -> None:
        if self._thread is not None:
            raise RuntimeError(f"{self.name}: already started")
        self._thread = threading.Thread(target=self._main, name=self.name, daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = DEFAULT_STOP_TIMEOUT_S) -> bool:
        """Ask the thread to end and join it; True when it has ended in time."""
        t0 = time.monotonic()
        self._stop.set()
        try:
            self._interrupt()
        except Exception:  # noqa: BLE001 - a failing cancel must not block shutdown
            log.debug("%s: interrupt failed", self.name, exc_info=True)
        if self._thread is not None:
            self._thread.join(timeout_s)
        self.last_stop_s = time.monotonic() - t0
        ended = not self.alive
        if not ended:
            log.warning("%s: thread did not end within %.1f s", self.name, timeout_s)
        return ended

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def __enter__(self) -> DriverThread:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    # -- for subclasses

    def _main(self) -> None:
        try:
            self._run()
        except Exception:  # noqa: BLE001 - a bug: log it where the journal shows it
            log.exception("%s: driver thread crashed", self.name)
            raise

    def _run(self) -> None:
        raise NotImplementedError

    def _interrupt(self) -> None:
        """Cancel a pending device read, if the transport can (optional)."""

    def _sleep(self, seconds: float) -> bool:
        """Wait `seconds` unless stopped; True when stop was requested."""
        return self._stop.wait(seconds)
