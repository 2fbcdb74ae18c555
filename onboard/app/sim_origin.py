"""`--sim-follow` without a configured EKF origin: offer the simulated
vehicle's start as the origin.

Without GPS the autopilot's EKF navigates only once it has an origin. On a
real vehicle that is `[mavlink] set_origin` with the site's coordinates
(onboard.outputs.mavlink_origin). In the closed loop with a simulator the
vehicle reports where it is, so when `set_origin` is off the origin is its
first reported position (the point placed at the scene's start): the
vehicle's true position relative to the EKF origin is then its position in
the scene relative to the start. SET_GPS_GLOBAL_ORIGIN goes out through the
shared link, each second until the autopilot answers GPS_GLOBAL_ORIGIN, 5
tries at most (the same handshake the MAVLink output uses), and again on
every new connection of the link (a restarted simulator has no origin).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from typing import Any

from drivers.fc_link import FcLink
from onboard.core.sources import DriverThread
from onboard.outputs.mavlink_origin import OriginHandshake
from onboard.outputs.settings import MavlinkConfig
from sim_replay.follow_state import VehicleTrack

log = logging.getLogger(__name__)


class OriginFromVehicle(DriverThread):
    def __init__(self, link: FcLink, track: VehicleTrack, cfg: MavlinkConfig) -> None:
        super().__init__("sim_origin")
        self.link = link
        self.track = track
        self.cfg = cfg
        self.handshake: OriginHandshake | None = None
        self._remove: Callable[[], None] | None = None

    def start(self) -> None:
        self._remove = self.link.add_listener(self._on_origin, ("GPS_GLOBAL_ORIGIN",))
        super().start()

    def stop(self, timeout_s: float = 5.0) -> bool:
        ended = super().stop(timeout_s)
        if self._remove is not None:
            self._remove()
            self._remove = None
        return ended

    def _on_origin(self, _msg: Any, _t_ns: int) -> None:
        if self.handshake is not None:
            self.handshake.on_confirmed()

    def _run(self) -> None:
        while not self.track.first.wait(0.1):
            if self.stopping:
                return
        a = self.track.anchor
        assert a is not None  # set with the first state
        cfg = dataclasses.replace(self.cfg, set_origin=True, origin_lat_deg=a.lat_e7 * 1e-7,
                                  origin_lon_deg=a.lon_e7 * 1e-7, origin_alt_m=a.alt_m)
        log.info("sim-follow: offering the vehicle's start as the EKF origin (%.7f, %.7f, %.2f m)",
                 cfg.origin_lat_deg, cfg.origin_lon_deg, cfg.origin_alt_m)
        generation = -1
        while not self.stopping:
            if self.link.generation != generation:  # a new connection: a restarted simulator
                generation = self.link.generation
                self.handshake = OriginHandshake(cfg)
            hs = self.handshake
            now = time.monotonic()
            if hs is not None and hs.due(now):
                for name, args in hs.messages(now, time.monotonic_ns() // 1000):
                    self.link.send(lambda mav, n=name, a=args: getattr(mav, n + "_send")(*a))
            if self._sleep(0.05):
                return
