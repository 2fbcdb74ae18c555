"""The zenoh output's link to what it connects to, as a device state
(onboard/core/device_state.py), like the drivers': one warning line when the
router goes, a reminder at most every 30 s while it is away, one line when it
is back; the health line and the zenoh status carry it in `devices`.

Only a session with `connect` endpoints has something to lose: a peer that
only listens has no state. The pose thread polls the session's routers and
peers (a local call, no traffic) every `POLL_S`; zenoh drops a transport as
soon as its TCP connection closes (a killed router: at once) or, silently
gone, when its lease expires (10 s, zenoh's default).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import zenoh

from onboard.core.device_state import DeviceSnapshot, DeviceState, State
from onboard.outputs.settings import ZenohConfig

log = logging.getLogger(__name__)

POLL_S = 0.25  # how often the routers and peers are looked at
OPEN_GRACE_S = 1.0  # a client still waiting for its router after this: "no device"


class ZenohLink:
    """`poll(session)` from the pose thread (session None: not open yet);
    `snapshot()` from the loop."""

    def __init__(self, cfg: ZenohConfig, clock: Callable[[], float] = time.monotonic) -> None:
        self.watched = bool(cfg.connect)
        self.client = cfg.mode == "client"
        device = "zenoh router" if self.client else "zenoh link"
        self.where = ", ".join(cfg.connect)
        self.state = DeviceState(device, self.where, clock=clock, logger=log)
        self._clock = clock
        self._start = clock()
        self._next = self._start
        self._was_up = False
        self.looks = 0  # times the link was looked at

    def poll(self, session: zenoh.Session | None) -> float:
        """Look at the link if it is time; the seconds until the next look."""
        now = self._clock()
        if not self.watched:
            return 3600.0
        if now < self._next:
            return self._next - now
        self._next = now + POLL_S
        self.looks += 1
        if session is None:
            if now - self._start >= OPEN_GRACE_S:
                self.state.set(State.NO_DEVICE, f"nothing answers at {self.where}; retrying "
                               "(poses and the status are not sent meanwhile)")
            return POLL_S
        info = session.info
        up = bool(info.routers_zid()) or (not self.client and bool(info.peers_zid()))
        if up:
            self._was_up = True
            self.state.set(State.STREAMING)
        else:
            what = "the router went away" if self._was_up else "nothing answers"
            self.state.set(State.NO_DEVICE, f"{what} at {self.where}; reconnecting "
                           "(poses and the status are lost meanwhile)")
        return POLL_S

    def snapshot(self) -> DeviceSnapshot:
        return self.state.snapshot()
