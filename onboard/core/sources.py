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
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Generic, Protocol, TypeVar

from onboard.core.camera import CameraModel
from onboard.core.messages import RgbdFrame

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


@dataclass(frozen=True)
class SlotStats:
    put: int = 0  # frames handed over by the driver
    taken: int = 0  # frames a consumer took
    dropped: int = 0  # frames replaced before anyone took them


class FrameSlot:
    """Holds the newest frame and its sequence number (1, 2, ...)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._frame: RgbdFrame | None = None
        self._seq = 0
        self._taken_seq = 0
        self._stats = SlotStats()
        self._closed = False

    def put(self, frame: RgbdFrame) -> int:
        with self._cond:
            dropped = 1 if self._frame is not None and self._taken_seq < self._seq else 0
            self._frame = frame
            self._seq += 1
            self._stats = SlotStats(self._stats.put + 1, self._stats.taken,
                                    self._stats.dropped + dropped)
            self._cond.notify_all()
            return self._seq

    def close(self) -> None:
        """No more frames will come (end of a replay): wake waiting consumers."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        with self._cond:
            return self._closed

    def take(self, after_seq: int = 0, timeout_s: float = 0.0) -> tuple[int, RgbdFrame] | None:
        """The newest frame if its sequence number is above `after_seq`,
        waiting up to `timeout_s` for one; None on timeout or when closed."""
        with self._cond:
            self._cond.wait_for(lambda: self._seq > after_seq or self._closed, timeout_s)
            if self._seq <= after_seq or self._frame is None:
                return None
            if self._taken_seq < self._seq:
                self._taken_seq = self._seq
                s = self._stats
                self._stats = SlotStats(s.put, s.taken + 1, s.dropped)
                self._cond.notify_all()  # a source in wait_taken
            return self._seq, self._frame

    def wait_taken(self, seq: int, timeout_s: float) -> bool:
        """Wait up to `timeout_s` until frame `seq` (or a newer one) was taken
        or the slot closed; True if it was."""
        with self._cond:
            return self._cond.wait_for(lambda: self._taken_seq >= seq or self._closed, timeout_s)

    @property
    def stats(self) -> SlotStats:
        with self._cond:
            return self._stats


class CameraSource(Protocol):
    """What the loop and the recorder need from a camera (OAK-D or replay)."""

    slot: FrameSlot  # the newest-frame slot (its stats count dropped frames)

    def start(self) -> None: ...

    def stop(self, timeout_s: float = ...) -> bool:
        """Stop the source's threads, join them; True when they ended in time."""
        ...

    def wait_camera(self, timeout_s: float) -> CameraModel | None:
        """The camera as delivered frames see it (undistorted intrinsics, depth
        scale of the raw depth, mount), once known; None on timeout."""
        ...

    def take(self, after_seq: int = 0, timeout_s: float = 0.0) -> tuple[int, RgbdFrame] | None:
        """The newest frame newer than `after_seq` (see FrameSlot.take)."""
        ...

    @property
    def exhausted(self) -> bool:
        """True once no further frame will ever come (end of a replay)."""
        ...
