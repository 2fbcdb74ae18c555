"""What each device or link is doing, told once and plainly.

Every driver (drivers/*) and the zenoh output's link to its router
(onboard/outputs/zenoh_link.py) owns a `DeviceState`: opening, no device,
open, streaming, silent, bad data, closed, with the cause. Pure (logging and
a lock only), so both layers share it; drivers/device_state.py re-exports it
with the drivers' logger. What the operator sees without
`-v` (warnings):

- the first failure (no device, silent, bad data): ONE line naming the
  device, its path or id and the cause;
- while it lasts, a reminder at most every `remind_s` (30 s);
- one line when the device streams again ("recovered").

A change from one failure to another (no device -> open but silent) is a new
line; the same failure again (each reopen attempt, even through "open") is
not. `snapshot()` and
`text()` are read by the health line, the zenoh status and the systemd
status (onboard.app.health). Thread-safe: the driver thread sets, the
loop reads.
"""

from __future__ import annotations

import enum
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

log = logging.getLogger(__name__)

REMIND_S = 30.0


class State(enum.Enum):
    OPENING = "opening"
    NO_DEVICE = "no device"
    OPEN = "open"  # opened, no valid data yet
    STREAMING = "streaming"
    SILENT = "silent"  # open, nothing arrives
    BAD_DATA = "bad data"  # bytes arrive, none of them valid samples
    CLOSED = "closed"

    @property
    def failed(self) -> bool:
        return self in (State.NO_DEVICE, State.SILENT, State.BAD_DATA)


@dataclass(frozen=True)
class DeviceSnapshot:
    device: str  # "OAK-D", "myAHRS+", "autopilot link"
    where: str  # path, id or URL
    state: State
    cause: str
    since_s: float  # monotonic time the state began
    failures: int  # failure spells so far
    first_failure_s: float | None  # monotonic time of the first failure line

    def text(self) -> str:
        cause = f" ({self.cause})" if self.cause and self.state is not State.STREAMING else ""
        return f"{self.device} {self.state.value}{cause}"


class DeviceState:
    def __init__(self, device: str, where: str, *, remind_s: float = REMIND_S,
                 clock: Callable[[], float] = time.monotonic,
                 logger: logging.Logger = log) -> None:
        self.device, self.where = device, where
        self.remind_s = remind_s
        self.clock = clock
        self.log = logger
        self._lock = threading.Lock()
        now = clock()
        self._state, self._cause, self._since = State.OPENING, "", now
        self._failing_since: float | None = None  # start of the current failure spell
        self._told: State | None = None  # the failure last told in this spell
        self._last_line = now
        self._failures = 0
        self._first_failure: float | None = None

    def set(self, state: State, cause: str = "") -> None:
        """Enter `state` (or stay in it): logs as the module doc says."""
        now = self.clock()
        line: str | None = None
        with self._lock:
            prev, changed = self._state, state is not self._state
            if changed:
                self._state, self._since = state, now
            self._cause = cause or (self._cause if not changed else "")
            if state.failed:
                if self._failing_since is None:
                    self._failing_since = now
                    self._failures += 1
                    if self._first_failure is None:
                        self._first_failure = now
                if state is not self._told:  # a reopen that fails the same way is no news
                    self._told = state
                    line = f"{self._head()}: {state.value}: {self._cause or 'no cause given'}"
                elif now - self._last_line >= self.remind_s:
                    line = (f"{self._head()}: still {state.value} after "
                            f"{now - self._failing_since:.0f} s: {self._cause}")
            elif state is State.STREAMING and self._failing_since is not None:
                line = (f"{self._head()}: recovered, streaming again after "
                        f"{now - self._failing_since:.1f} s ({prev.value} before)")
                self._failing_since = self._told = None
            elif state is State.CLOSED:
                self._failing_since = self._told = None
            if line is not None:
                self._last_line = now
        if line is not None:
            self.log.warning("%s", line)

    def _head(self) -> str:
        return f"{self.device} {self.where}" if self.where else self.device

    @property
    def state(self) -> State:
        with self._lock:
            return self._state

    def snapshot(self) -> DeviceSnapshot:
        with self._lock:
            return DeviceSnapshot(self.device, self.where, self._state, self._cause, self._since,
                                  self._failures, self._first_failure)

    def text(self) -> str:
        return self.snapshot().text()
