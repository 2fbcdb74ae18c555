"""The EKF-origin handshake: without GPS the autopilot's EKF has no global
origin, so the feed offers one (`[mavlink] set_origin`, origin_* keys):
SET_GPS_GLOBAL_ORIGIN and SET_HOME_POSITION, repeated each second until the
autopilot confirms with GPS_GLOBAL_ORIGIN, 5 tries at most. Pure: the link
thread (onboard.outputs.mavlink) asks what to send and when.
"""

from __future__ import annotations

import logging
from typing import Any

from onboard.outputs.settings import MavlinkConfig

log = logging.getLogger(__name__)

RETRY_S = 1.0
MAX_TRIES = 5


class OriginHandshake:
    def __init__(self, cfg: MavlinkConfig) -> None:
        self.cfg = cfg
        self.done = not cfg.set_origin
        self.tries = 0
        self.next_s = 0.0  # monotonic time of the next try

    def due(self, now_s: float) -> bool:
        return not self.done and now_s >= self.next_s

    def messages(self, now_s: float, t_us: int) -> list[tuple[str, tuple[Any, ...]]]:
        """This try's messages as (pymavlink message name, send arguments);
        the next try is a second later, none after the last."""
        c = self.cfg
        lat, lon = round(c.origin_lat_deg * 1e7), round(c.origin_lon_deg * 1e7)
        alt = round(c.origin_alt_m * 1e3)
        self.tries += 1
        self.next_s = now_s + RETRY_S
        if self.tries >= MAX_TRIES:
            self.done = True
        return [
            ("set_gps_global_origin", (c.system_id, lat, lon, alt, t_us)),
            ("set_home_position", (c.system_id, lat, lon, alt, 0.0, 0.0, 0.0,
                                   [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, t_us)),
        ]

    def on_confirmed(self) -> None:
        """The autopilot sent GPS_GLOBAL_ORIGIN."""
        if not self.done:
            self.done = True
            log.info("autopilot confirmed the EKF origin")
