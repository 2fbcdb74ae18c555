"""The camera source interface: a newest-frame slot, stale frames dropped.

A camera driver (the OAK-D, or the replay camera in sim_replay.sources)
puts every frame it completes into a `FrameSlot`; the consumer (the loop or
the recorder) takes the newest one. A frame replaced before anyone took it is
dropped and counted, never queued: latency beats completeness for a flight
controller.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from onboard.frames import RgbdFrame

if TYPE_CHECKING:
    from sim_replay.tum import CameraModel


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
            return self._seq, self._frame

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
