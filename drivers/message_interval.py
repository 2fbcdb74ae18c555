"""Keep a message streaming from the autopilot (or a simulator) over the FC link.

COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL (511, param1 = message id, param2 =
interval in us) on every new connection of the link and again every
`retry_s` while the stream is missing (an autopilot reboot forgets it; a
GCS may override rates). Used by `nislam run --sim-follow` to ask ArduPilot
SITL for SIM_STATE; drivers/autopilot_attitude.py does the same for its
ATTITUDE_QUATERNION with its own clock handling.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from drivers.fc_link import FcLink
from onboard.core.sources import DriverThread

log = logging.getLogger(__name__)

MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_RESULT_ACCEPTED = 0
MESSAGE_IDS = {"SIM_STATE": 108, "HIL_STATE_QUATERNION": 115, "ATTITUDE_QUATERNION": 31}


class MessageInterval(DriverThread):
    """Requests `message` at `rate_hz` from (target_system, target_component)."""

    def __init__(self, link: FcLink, message: str, rate_hz: float, *, target_system: int = 1,
                 target_component: int = 1, retry_s: float = 1.0,
                 clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        super().__init__(f"message_interval:{message}")
        self.link = link
        self.message = message
        self.msg_id = MESSAGE_IDS[message]
        self.interval_us = int(round(1e6 / rate_hz))
        self.target_system = target_system
        self.target_component = target_component
        self.retry_ns = int(retry_s * 1e9)
        self.clock_ns = clock_ns
        self.requests = 0
        self.received = 0
        self._last_ns: int | None = None
        self._refused = False
        self._remove: Callable[[], None] | None = None

    def start(self) -> None:
        self._remove = self.link.add_listener(self._on_message, (self.message, "COMMAND_ACK"))
        super().start()

    def stop(self, timeout_s: float = 5.0) -> bool:
        ended = super().stop(timeout_s)
        if self._remove is not None:
            self._remove()
            self._remove = None
        return ended

    def _run(self) -> None:
        generation = -1
        last_request = 0
        while not self.stopping:
            now = self.clock_ns()
            last = self._last_ns
            streaming = last is not None and now - last < self.retry_ns
            fresh = self.link.generation != generation
            if self.link.connected.is_set() and (
                    fresh or (not streaming and now - last_request >= self.retry_ns)):
                if self._request():
                    generation = self.link.generation
                    last_request = now
            if self._sleep(0.1):
                return

    def _request(self) -> bool:
        sent = self.link.send(lambda mav: mav.command_long_send(
            self.target_system, self.target_component, MAV_CMD_SET_MESSAGE_INTERVAL, 0,
            self.msg_id, self.interval_us, 0, 0, 0, 0, 0))
        self.requests += int(sent)
        return sent

    def _on_message(self, msg: Any, t_ns: int) -> None:  # the link's reader thread
        if msg.get_type() == "COMMAND_ACK":
            if (msg.command == MAV_CMD_SET_MESSAGE_INTERVAL and msg.result != MAV_RESULT_ACCEPTED
                    and not self._refused):
                self._refused = True
                log.warning("the autopilot refused SET_MESSAGE_INTERVAL(%s): result %s",
                            self.message, msg.result)
            return
        self.received += 1
        self._last_ns = t_ns
