"""The last check before a pose leaves the vehicle: can the motion model
explain it? Pure (no I/O); the service runs every TrackResult through it.

A tracker that loses and re-finds its key after a gap can come back with a
pose that is wrong by decimetres while its own match score looks fine (a
replay with one garbage frame: 0.49 m after 0.33 s while the vehicle moved
0.03 m). Over a gap that short a vehicle accelerating at up to 4 m/s^2 could
drift that far from a constant-velocity guess, so one pose cannot tell; the
velocity after the gap can. The gate:

1. predicts each pose from the last accepted ones at constant velocity v0
   (estimated over `velocity_window_s`) and allows, after dt,

       base_m + v_noise * dt + a_trigger / 2 * dt * (window + dt)

   (noise, the velocity's noise, and how far a vehicle accelerating at
   `trigger_accel_m_s2` strays, the velocity being the window's mean). A pose
   outside that, or after a gap over `max_gap_s`, starts a check;
2. during the check the poses are withheld (`withheld`; untrusted, counted:
   the service sends no pose for them, and does not count them as lost)
   until `settle_frames` more agree with it; their velocity v1 is then
   known, and the step d across the gap T must satisfy the two-sided bound

       |d - (v0 + v1) / 2 * T| <= base_m + max_accel / 4 * T^2 + noise * T

   (a vehicle that starts at v0 and ends at v1 strays at most a T^2 / 4 from
   the trapezoid between them, bang-bang acceleration). Within it the poses
   are trusted again as they are (a false trigger costs `settle_frames`
   withheld poses, nothing else); beyond it the tracker jumped: counted, and
   the poses from then on go out with reset_counter one higher, so the
   autopilot's EKF takes the new position as a reset, not as motion.

A tracker reset (its own reset_counter moves) restarts the gate.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from onboard.core.messages import TrackResult

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GateSettings:
    max_accel_m_s2: float = 4.0  # an indoor multirotor stays below ~0.4 g
    trigger_accel_m_s2: float = 2.0  # tighter: a false trigger costs settle_frames, not a reset
    pose_sigma_m: float = 0.01  # tracker position noise per frame (NI-SLAM ~1 cm)
    max_gap_s: float = 1.0  # beyond this one pose cannot be judged: check the next ones
    settle_frames: int = 2  # agreeing poses after a suspect one before the verdict
    velocity_window_s: float = 0.2

    @property
    def base_m(self) -> float:  # 4 sigma of the difference of two poses
        return 4.0 * math.sqrt(2.0) * self.pose_sigma_m

    def v_noise(self, baseline_s: float) -> float:  # 3 sigma of a velocity over the baseline
        return 3.0 * math.sqrt(2.0) * self.pose_sigma_m / max(baseline_s, 1e-3)


@dataclass
class GateStats:
    checked: int = 0  # trusted results looked at
    rejected: int = 0  # ... sent as untrusted by the gate (while checking)
    checks: int = 0  # suspect poses (a step beyond the trigger, or after a long gap)
    jumps: int = 0  # checks that found a step the motion model cannot explain
    resets: int = 0  # reset_counter steps added (one per jump)
    last_reason: str | None = None

    def as_dict(self) -> dict[str, object]:
        return dataclasses.asdict(self)


Pose = tuple[float, np.ndarray]  # (t_s, p_W_m)


class PoseGate:
    """`check(result)` -> the result to publish (untrusted while a suspect
    step is checked; reset_counter raised by the gate's resets)."""

    def __init__(self, settings: GateSettings = GateSettings()) -> None:
        self.s = settings
        self.stats = GateStats()
        self._history: deque[Pose] = deque()  # accepted poses, the last velocity window
        self._hold: list[Pose] | None = None  # poses since a suspect step
        self._hold_why = ""
        self._tracker_counter: int | None = None
        self.withheld = False  # the last result was withheld while a step is checked

    def check(self, result: TrackResult) -> TrackResult:
        if self._tracker_counter is not None and result.reset_counter != self._tracker_counter:
            self._history.clear()  # the tracker's world restarted: nothing to compare with
            self._hold = None
        self._tracker_counter = result.reset_counter
        self.withheld = False
        out = self._check(result)
        if self.stats.resets:
            out = dataclasses.replace(out, reset_counter=out.reset_counter + self.stats.resets)
        return out

    def _check(self, r: TrackResult) -> TrackResult:
        if not r.trusted or r.p_W_m is None:
            return r
        self.stats.checked += 1
        pose = (float(r.t_s), np.asarray(r.p_W_m, dtype=np.float64))
        if self._hold is not None:
            return self._checking(r, pose)
        if not self._history:
            self._accept(pose)
            return r
        dt = pose[0] - self._history[-1][0]
        if dt > self.s.max_gap_s:
            return self._suspect(r, pose, f"pose after a {dt:.1f} s gap")
        miss, allowed = self._predict(self._history, pose, self.s.trigger_accel_m_s2)
        if miss <= allowed:
            self._accept(pose)
            return r
        return self._suspect(r, pose, f"step {miss:.2f} m off the motion after {dt:.2f} s")

    def _suspect(self, r: TrackResult, pose: Pose, why: str) -> TrackResult:
        self.stats.checks += 1
        self._hold, self._hold_why = [pose], why
        return self._reject(r, f"checking a {why}")

    def _checking(self, r: TrackResult, pose: Pose) -> TrackResult:
        hold = self._hold
        assert hold is not None
        miss, allowed = self._predict(hold, pose, self.s.max_accel_m_s2)
        if miss > allowed:  # the suspect run itself is not smooth: start it again here
            self._hold = [pose]
            return self._reject(r, f"checking a {self._hold_why} (not settled)")
        hold.append(pose)
        if len(hold) <= self.s.settle_frames:
            return self._reject(r, f"checking a {self._hold_why}")
        if not self._explained(hold):
            self.stats.resets += 1
            self.stats.jumps += 1
            self.stats.last_reason = f"{self._hold_why}: reset"
            log.warning("pose jump the motion model cannot explain (%s): %d poses withheld, "
                        "then sent as a reset (reset_counter +%d)", self._hold_why, len(hold) - 1,
                        self.stats.resets)
        self._history = deque(hold)
        self._hold = None
        return r

    def _explained(self, run: list[Pose]) -> bool:
        """The two-sided bound across the gap between the history and `run`."""
        s = self.s
        (t0, p0), (t1, p1) = self._history[-1], run[0]
        v0, b0 = self._velocity(self._history)
        v1 = (run[-1][1] - run[0][1]) / max(run[-1][0] - run[0][0], 1e-3)
        b1 = run[-1][0] - run[0][0]
        T = max(t1 - t0, 0.0)
        off = float(np.linalg.norm(p1 - p0 - 0.5 * (v0 + v1) * T))
        v_noise = 0.5 * (s.v_noise(b0) if b0 > 0 else 0.0) + 0.5 * s.v_noise(b1)
        return off <= s.base_m + 0.25 * s.max_accel_m_s2 * T * T + v_noise * T

    def _velocity(self, hist) -> tuple[np.ndarray, float]:
        """(mean velocity over the window ending at the newest pose, its baseline [s])."""
        t_last, p_last = hist[-1]
        for t_old, p_old in hist:  # the oldest pose inside the window
            if t_last - t_old <= self.s.velocity_window_s:
                if t_last - t_old > 1e-3:
                    return (p_last - p_old) / (t_last - t_old), t_last - t_old
                break
        return np.zeros(3), 0.0

    def _predict(self, hist, pose: Pose, accel: float) -> tuple[float, float]:
        """(distance from the constant-velocity prediction, what the model allows)."""
        s = self.s
        t_last, p_last = hist[-1]
        dt = max(pose[0] - t_last, 0.0)
        v, base_s = self._velocity(hist)
        # No velocity yet (one pose): anything up to a fast indoor flight (3 m/s).
        v_err = s.v_noise(base_s) if base_s > 0 else 3.0
        miss = float(np.linalg.norm(pose[1] - (p_last + v * dt)))
        allowed = s.base_m + v_err * dt + 0.5 * accel * dt * (base_s + dt)
        return miss, allowed

    def _accept(self, pose: Pose) -> None:
        self._history.append(pose)
        while (len(self._history) > 2
               and pose[0] - self._history[1][0] >= self.s.velocity_window_s):
            self._history.popleft()

    def _reject(self, r: TrackResult, reason: str) -> TrackResult:
        self.withheld = True
        self.stats.rejected += 1
        self.stats.last_reason = reason
        return dataclasses.replace(r, trusted=False, p_W_m=None, R_W_C=None, lost_reason=reason)
