"""The service's health: starting, tracking, degraded or lost, from sensor
freshness and tracker quality. Pure: time comes in with every update.

    STARTING   no trusted pose yet (sensors coming up, first key frame);
               after `start_grace_s` without a frame it is LOST instead
    TRACKING   the newest result is trusted, quality >= degraded_quality,
               the primary tracker runs and frames arrive on time
    DEGRADED   trusted, but quality below degraded_quality (back at +5),
               the fallback tracker runs (no attitude), or the last frame
               gap was longer than `degraded_gap_s`; and for `recover_s`
               after any of these or a LOST spell ended ("recovering")
    LOST       the newest result is untrusted after a pose was had, or no
               frame for `frame_timeout_s`

The recovery dwell keeps a stuttering camera or a flickering match from
flapping the state (each change is a STATUSTEXT on the telemetry link): the
state turns good only after it has stayed good for `recover_s`.

The MAVLink heartbeat (system_status) and the zenoh status carry the state;
with `devices` (each driver's state, drivers/device_state.py) every report
carries those too, and a driver that fails names itself in the reason
("lost (no frames for 2.1 s; OAK-D no device (...))").
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from onboard.core.messages import Health, HealthReport, TrackResult
from onboard.fusion.fused import fusion_text

QUALITY_HYSTERESIS = 5  # as the MAVLink feed's DEGRADED <-> ACTIVE


@dataclass(frozen=True)
class HealthThresholds:
    """From [service] and [mavlink] degraded_quality (their defaults live there)."""

    frame_timeout_s: float
    degraded_gap_s: float
    degraded_quality: int
    start_grace_s: float
    recover_s: float = 1.0  # problems gone this long before DEGRADED or LOST turns TRACKING


class HealthMonitor:
    """Feed it every loop turn; `report` is the current state."""

    def __init__(self, thresholds: HealthThresholds, start_s: float,
                 devices: Callable[[], Sequence[Any]] | None = None) -> None:
        self.th = thresholds
        self.devices = devices  # -> snapshots with .text() and .state.failed
        self.start_s = start_s
        self.report = HealthReport(Health.STARTING, "waiting for sensors")
        self._last_frame_s: float | None = None
        self._gap_s = 0.0
        self._had_pose = False
        self._result: TrackResult | None = None
        self._fallback: str | None = None
        self._problem: tuple[float, str] | None = None  # (when, what) the last problem was seen
        self._announced = False  # the first report counts as a change: outputs announce it

    def on_frame(self, now_s: float, result: TrackResult, fallback: str | None) -> HealthReport:
        """A frame was tracked at `now_s` (our clock); `fallback` names the
        fallback tracker when it produced `result`."""
        if self._last_frame_s is not None:
            self._gap_s = now_s - self._last_frame_s
        self._last_frame_s = now_s
        self._result = result
        self._fallback = fallback
        self._had_pose = self._had_pose or result.trusted
        return self._set(*self._classify(now_s))

    def on_idle(self, now_s: float) -> HealthReport:
        """A loop turn without a new frame."""
        return self._set(*self._classify(now_s))

    def _classify(self, now_s: float) -> tuple[Health, str]:
        state, reason = self._classify_now(now_s)
        if state in (Health.DEGRADED, Health.LOST):
            self._problem = (now_s, reason)
        elif state is Health.TRACKING and self._problem is not None:
            seen_s, what = self._problem
            if now_s - seen_s < self.th.recover_s:
                return Health.DEGRADED, f"recovering ({what})"
        return state, reason

    def _classify_now(self, now_s: float) -> tuple[Health, str]:
        """The state this instant calls for, before the recovery dwell."""
        th = self.th
        if self._last_frame_s is None:
            waited = now_s - self.start_s
            if waited > th.start_grace_s:
                return Health.LOST, f"no frames from the camera for {waited:.0f} s"
            return Health.STARTING, "waiting for the camera"
        silence = now_s - self._last_frame_s
        if silence > th.frame_timeout_s:
            return Health.LOST, f"no frames for {silence:.1f} s"
        r = self._result
        assert r is not None
        if not r.trusted:
            if not self._had_pose and self.report.state is not Health.LOST:
                return Health.STARTING, f"initialising ({r.lost_reason or 'no pose yet'})"
            return Health.LOST, r.lost_reason or "untrusted"
        problems = []
        floor = th.degraded_quality
        if self.report.state is Health.DEGRADED:
            floor += QUALITY_HYSTERESIS
        if r.quality < floor:
            problems.append(f"quality {r.quality}")
        if self._fallback is not None:
            problems.append(f"fallback tracker {self._fallback} (no attitude)")
        if self._gap_s > th.degraded_gap_s:
            problems.append(f"frame gap {self._gap_s:.2f} s")
        fused = f"; {fusion_text(r)}" if r.contributors or r.left_out else ""
        if problems:
            return Health.DEGRADED, ", ".join(problems) + fused
        return Health.TRACKING, f"quality {r.quality}{fused}"

    def _set(self, state: Health, reason: str) -> HealthReport:
        changed = state is not self.report.state or not self._announced
        self._announced = True
        texts: tuple[str, ...] = ()
        if self.devices is not None:
            snaps = self.devices()
            texts = tuple(d.text() for d in snaps)
            failing = [d.text() for d in snaps if d.state.failed]
            if failing and state is not Health.TRACKING:
                reason = f"{reason}; {'; '.join(failing)}"
        self.report = HealthReport(state, reason, changed, texts)
        return self.report
