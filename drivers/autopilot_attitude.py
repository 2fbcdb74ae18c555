"""The autopilot as an attitude source: ATTITUDE_QUATERNION over the FC link.

- Requests ATTITUDE_QUATERNION (id 31) at the configured rate with COMMAND_LONG
  MAV_CMD_SET_MESSAGE_INTERVAL (511, param1 = 31, param2 = interval in us),
  again until the autopilot acknowledges it, on every new connection of the
  link, and whenever the stream stops (an autopilot reboot forgets it; a GCS
  may override rates).
- `time_boot_ms` is the autopilot's clock. `BootClock` maps it onto ours: the
  offset is the minimum of (arrival - boot time) over a sliding window, the
  least-delayed message's view, which follows slow drift between the two
  crystals and restarts when the boot time jumps back (a reboot). The
  remaining fixed delay inside the autopilot is `latency_ms` from config.
- q1..q4 are w, x, y, z (FRD body in NED): turned into xyzw, then into body
  samples with the configured AHRS-to-body rotation (identity: the autopilot
  IS the body).
"""

from __future__ import annotations

import collections
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from drivers.fc_link import FcLink
from onboard.core.attitude import AttitudeSample, to_body_sample
from onboard.core.rotations import IDENTITY_Q_XYZW, Quat
from onboard.core.sources import Counters, DriverThread

log = logging.getLogger(__name__)

MAV_CMD_SET_MESSAGE_INTERVAL = 511
MSG_ID_ATTITUDE_QUATERNION = 31
MAV_RESULT_ACCEPTED = 0


class BootClock:
    """Autopilot boot time (ms) -> our monotonic clock (ns)."""

    def __init__(self, window_s: float = 10.0, reboot_jump_s: float = 1.0) -> None:
        self.window_ns = int(window_s * 1e9)
        self.reboot_jump_ms = reboot_jump_s * 1e3
        self._window: collections.deque[tuple[int, int]] = collections.deque()
        self._last_boot_ms: float | None = None
        self.resets = 0

    @property
    def offset_ns(self) -> int | None:
        return self._window[0][1] if self._window else None

    def to_host_ns(self, time_boot_ms: float, arrival_ns: int) -> int:
        boot_ns = int(round(time_boot_ms * 1e6))
        last = self._last_boot_ms
        if last is not None and time_boot_ms < last - self.reboot_jump_ms:
            self._window.clear()  # the autopilot rebooted: its clock started again
            self.resets += 1
        self._last_boot_ms = time_boot_ms
        candidate = arrival_ns - boot_ns
        w = self._window
        while w and w[-1][1] >= candidate:  # monotonic deque: O(1) sliding minimum
            w.pop()
        w.append((arrival_ns, candidate))
        while w[0][0] < arrival_ns - self.window_ns:
            w.popleft()
        return boot_ns + w[0][1]


@dataclass(frozen=True)
class AutopilotStats:
    requests: int = 0  # SET_MESSAGE_INTERVAL commands sent
    acks: int = 0  # ... accepted
    nacks: int = 0  # ... refused (result != ACCEPTED)
    samples: int = 0
    ignored: int = 0  # ATTITUDE_QUATERNION from another system/component
    clock_resets: int = 0  # autopilot reboots seen in time_boot_ms


class AutopilotAttitude(DriverThread):
    """Attitude samples from the autopilot on `link`, handed to `sink`.

    The link's reader thread parses and stamps; this object's own thread only
    (re)sends the interval request.
    """

    def __init__(
        self,
        link: FcLink,
        sink: Callable[[AttitudeSample], object],
        *,
        rate_hz: float = 50.0,
        target_system: int = 1,
        target_component: int = 1,
        latency_ms: float = 0.0,
        q_B_A_xyzw: Quat = IDENTITY_Q_XYZW,
        retry_s: float = 1.0,
        clock_window_s: float = 10.0,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        super().__init__("autopilot_attitude")
        self.link = link
        self.sink = sink
        self.interval_us = int(round(1e6 / rate_hz))
        self.target_system = target_system
        self.target_component = target_component
        self.latency_ns = int(round(latency_ms * 1e6))
        self.q_B_A_xyzw = q_B_A_xyzw
        self.retry_ns = int(retry_s * 1e9)
        self.boot_clock = BootClock(clock_window_s)
        self.clock_ns = clock_ns
        self.counters: Counters[AutopilotStats] = Counters(AutopilotStats())
        self._remove_listener: Callable[[], None] | None = None
        self._acked = False
        self._last_sample_ns: int | None = None

    @property
    def stats(self) -> AutopilotStats:
        return self.counters.snapshot()

    def start(self) -> None:
        self._remove_listener = self.link.add_listener(
            self._on_message, ("ATTITUDE_QUATERNION", "COMMAND_ACK"))
        super().start()

    def stop(self, timeout_s: float = 5.0) -> bool:
        ended = super().stop(timeout_s)
        if self._remove_listener is not None:
            self._remove_listener()
            self._remove_listener = None
        return ended

    # -- request thread

    def _run(self) -> None:
        # Request on every new connection; then again every retry_s while the
        # stream is missing, or (a few times) while the request is unanswered.
        tick_s = min(0.1, self.retry_ns * 0.5e-9)
        requested_generation = -1
        last_request_ns = 0
        unanswered = 0
        while not self.stopping:
            now = self.clock_ns()
            due = now - last_request_ns >= self.retry_ns
            last_sample = self._last_sample_ns
            streaming = last_sample is not None and now - last_sample < self.retry_ns
            fresh = self.link.generation != requested_generation
            if self._acked:
                unanswered = 0
            if self.link.connected.is_set() and (
                fresh or (due and not streaming) or (due and not self._acked and unanswered < 3)
            ):
                if fresh:
                    self._acked = False
                    unanswered = 0
                if self._request():
                    requested_generation = self.link.generation
                    last_request_ns = now
                    unanswered += 0 if self._acked else 1
            if self._sleep(tick_s):
                break

    def _request(self) -> bool:
        sent = self.link.send(lambda mav: mav.command_long_send(
            self.target_system, self.target_component, MAV_CMD_SET_MESSAGE_INTERVAL, 0,
            MSG_ID_ATTITUDE_QUATERNION, self.interval_us, 0, 0, 0, 0, 0))
        if sent:
            self.counters.bump(requests=1)
        return sent

    # -- link reader thread

    def _on_message(self, msg: Any, t_ns: int) -> None:
        if msg.get_srcSystem() != self.target_system or (
            self.target_component and msg.get_srcComponent() != self.target_component
        ):
            if msg.get_type() == "ATTITUDE_QUATERNION":
                self.counters.bump(ignored=1)
            return
        if msg.get_type() == "COMMAND_ACK":
            if msg.command == MAV_CMD_SET_MESSAGE_INTERVAL:
                if msg.result == MAV_RESULT_ACCEPTED:
                    self._acked = True
                    self.counters.bump(acks=1)
                else:
                    self.counters.bump(nacks=1)
                    log.warning("autopilot refused SET_MESSAGE_INTERVAL(ATTITUDE_QUATERNION): "
                                "result %s", msg.result)
            return
        resets = self.boot_clock.resets
        t_host = self.boot_clock.to_host_ns(msg.time_boot_ms, t_ns) - self.latency_ns
        if self.boot_clock.resets != resets:
            log.warning("autopilot time_boot_ms jumped back: it rebooted; clock mapping restarted")
            self.counters.bump(clock_resets=1)
        q_xyzw = (msg.q2, msg.q3, msg.q4, msg.q1)  # MAVLink sends w, x, y, z
        sample = to_body_sample(t_host, q_xyzw, self.q_B_A_xyzw)
        self._last_sample_ns = t_ns
        if sample is not None:
            self.sink(sample)
            self.counters.bump(samples=1)
