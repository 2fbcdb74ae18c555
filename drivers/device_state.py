"""The drivers' device states: onboard/core/device_state.py (shared with the
zenoh output's link), logged under `drivers.device_state` so that
`logging.getLogger("drivers")` still governs the drivers' lines (`nislam
doctor` quiets them while it prints its table)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from onboard.core.device_state import REMIND_S, DeviceSnapshot, State
from onboard.core.device_state import DeviceState as _DeviceState

__all__ = ["REMIND_S", "DeviceSnapshot", "DeviceState", "State"]

log = logging.getLogger(__name__)


class DeviceState(_DeviceState):
    def __init__(self, device: str, where: str, *, remind_s: float = REMIND_S,
                 clock: Callable[[], float] = time.monotonic,
                 logger: logging.Logger = log) -> None:
        super().__init__(device, where, remind_s=remind_s, clock=clock, logger=logger)
