"""The attitude interface every AHRS driver feeds and the tracker reads.

Drivers turn what their sensor reports (the AHRS axes A in the sensor's world)
into `AttitudeSample`s of the vehicle body B in the AHRS world W (gravity
aligned, z down) with `to_body_sample`, using the AHRS-to-body rotation from
config, and push them into an `AttitudeBuffer`. The buffer implements
`onboard.core.messages.AttitudeSource`: `rotation_at(t_s)` fits the samples
within `smoothing_s` of `t_s` (onboard.core.attitude_smoothing) or slerps
between the two around it, and returns R_W_C = R_W_B(t) R_B_C with the camera
mount, or None ("no attitude") when the query lies outside the buffered span
or the two samples around it are further apart than `max_gap_s` (an outage).
A frame captured while the AHRS was talking keeps its attitude however late
the loop gets to it (a stalled machine, a busy core); one captured after the
AHRS went silent lies beyond the newest sample and has none.

All stamps are capture times on one monotonic clock in nanoseconds
(`time.monotonic_ns` live; a replay clock on the recording's time base in
replay). `rotation_at` takes seconds on the same clock, as RgbdFrame.t_s.

Live (`now_ns` given), a sample stamped more than `jump_s` away from that
clock at its push is a time jump of the AHRS's stamps (a device clock or its
mapping gone wrong while the camera's stamps stay right): it is dropped and
counted, never stored. Stored, a jumped-ahead stamp would open a gap no frame
gets an attitude from, and once frames caught up with it, hand them the
attitude of seconds before; a jumped-back stamp would, after the
out-of-order rejections, do the same for ever. Dropped, frames simply get no
attitude until the stamps are sane again (the tracker then sends nothing
trusted), and `stamps` (onboard/core/device_state.py) tells it in one line
and its recovery in another. Within `jump_s` a stamp is not told from
latency and jitter: that bounds the attitude error a jump can cause.
"""

from __future__ import annotations

import bisect
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from onboard.core.device_state import DeviceState, State
from onboard.core.attitude_smoothing import DEFAULT_HALF_S, Window
from onboard.core.rotations import (
    Quat,
    quat_conj,
    quat_mul,
    quat_normalized,
    quat_slerp,
    quat_to_matrix,
)


@dataclass(frozen=True)
class AttitudeSample:
    """Body orientation at a capture time: `q_W_B_xyzw` rotates body vectors
    into the AHRS world W; `t_ns` is the capture time on the monotonic clock."""

    t_ns: int
    q_W_B_xyzw: Quat

    @property
    def t_s(self) -> float:
        return self.t_ns * 1e-9


@dataclass(frozen=True)
class BufferStats:
    pushed: int = 0
    rejected_out_of_order: int = 0  # stamp not after the newest sample
    rejected_invalid: int = 0  # non-finite or zero-norm quaternion
    rejected_time_jump: int = 0  # stamped more than jump_s from the clock (live)


# --------------------------------------------------------------------------- quaternions


def to_body_sample(t_ns: int, q_W_A_xyzw: Quat, q_B_A_xyzw: Quat) -> AttitudeSample | None:
    """The body's attitude from the AHRS's: R_W_B = R_W_A R_A_B, with R_A_B
    the inverse of the configured AHRS-to-body rotation R_B_A. None when the
    reported quaternion is not a rotation."""
    q = quat_normalized(q_W_A_xyzw)
    if q is None:
        return None
    return AttitudeSample(int(t_ns), quat_mul(q, quat_conj(q_B_A_xyzw)))


# --------------------------------------------------------------------------- buffer


class AttitudeBuffer:
    """Bounded, thread-safe store of body attitude samples; an AttitudeSource.

    `push` is called by one driver thread, `rotation_at` by the loop. The lock
    guards two list operations at a time, never a device read.
    """

    def __init__(
        self,
        R_B_C: np.ndarray | None = None,
        capacity: int = 1024,
        max_gap_s: float = 0.1,
        now_ns: Callable[[], int] | None = None,
        jump_s: float = 2.0,
        label: str = "AHRS",
        smoothing_s: float = DEFAULT_HALF_S,
        smoothing_max_s: float = 0.0,
        noise_sd_deg: float = 0.0,
    ) -> None:
        """`smoothing_s`: half window of the local fit rotation_at makes where
        the samples are dense (onboard.core.attitude_smoothing); 0: the slerp.
        `noise_sd_deg`: the AHRS's white noise per sample and axis; with it
        the window widens up to +-`smoothing_max_s` as far as the data allow
        (attitude_smoothing.adaptive_fit)."""
        if capacity < 2:
            raise ValueError("attitude buffer capacity must be >= 2")
        self.R_B_C = np.eye(3) if R_B_C is None else np.asarray(R_B_C, dtype=np.float64)
        self.capacity = int(capacity)
        self.max_gap_s = float(max_gap_s)
        self.smoothing_s = float(smoothing_s)
        self._window = Window(smoothing_s, smoothing_max_s, noise_sd_deg)
        self._lock = threading.Lock()
        self._t_s: list[float] = []
        self._samples: list[AttitudeSample] = []
        self._stats = BufferStats()
        self._new = threading.Condition(self._lock)
        self.now_ns = now_ns  # the stamps' clock, live; None: no time-jump check (replay)
        self.jump_ns = int(jump_s * 1e9)
        self.stamps = DeviceState(f"{label} stamps", "")

    # -- writing (driver threads)

    def push(self, sample: AttitudeSample) -> bool:
        """Store a sample; False (and counted) if it is not newer than the
        newest one or its quaternion is not a rotation."""
        if self.now_ns is not None:
            skew_ns = sample.t_ns - self.now_ns()
            if abs(skew_ns) > self.jump_ns:
                with self._lock:
                    self._stats = _bump(self._stats, rejected_time_jump=1)
                self.stamps.set(State.BAD_DATA, (
                    f"time jump: stamped {skew_ns * 1e-9:+.1f} s from the clock; its samples "
                    "are dropped, frames get no attitude meanwhile"))
                return False
            self.stamps.set(State.STREAMING)
        q = quat_normalized(sample.q_W_B_xyzw)
        with self._lock:
            if q is None:
                self._stats = _bump(self._stats, rejected_invalid=1)
                return False
            if self._samples and sample.t_ns <= self._samples[-1].t_ns:
                self._stats = _bump(self._stats, rejected_out_of_order=1)
                return False
            self._samples.append(AttitudeSample(sample.t_ns, q))
            self._t_s.append(sample.t_ns * 1e-9)
            if len(self._samples) >= 2 * self.capacity:  # trim in chunks: amortised O(1)
                del self._samples[: -self.capacity]
                del self._t_s[: -self.capacity]
            self._stats = _bump(self._stats, pushed=1)
            self._new.notify_all()
        return True


    # -- reading (the loop, the recorder)

    @property
    def widens(self) -> bool:
        """Whether look-ups may widen the fit (a stated noise and room to widen)."""
        return self._window.widens

    def rotation_at(self, t_s: float, widen: bool = True) -> np.ndarray | None:
        """R_W_C (3x3) at `t_s`, or None: no attitude there (see module doc).
        `widen` False: the fit over +-smoothing_s alone (without_widening)."""
        q = self.body_quat_at(t_s)
        if q is None:
            return None
        r_w_b = quat_to_matrix(q)
        if self.smoothing_s > 0.0:
            w = self._window
            ts, qs = self._body_quats_between(t_s - w.widest_s, t_s + w.widest_s)
            delta = w.fit(t_s, ts, qs, q, widen)
            if delta is not None:  # fitted in the body's tangent space, then the mount
                r_w_b = r_w_b @ delta
        return r_w_b @ self.R_B_C

    def body_rotation_at(self, t_s: float) -> np.ndarray | None:
        q = self.body_quat_at(t_s)
        return None if q is None else quat_to_matrix(q)

    def body_quat_at(self, t_s: float) -> Quat | None:
        """q_W_B_xyzw at `t_s` slerped between its neighbours, or None."""
        with self._lock:
            ts = self._t_s
            n = len(ts)
            if n == 0:
                return None
            lo = max(0, n - self.capacity)
            if not (ts[lo] <= t_s <= ts[-1]):  # also rejects NaN
                return None
            i = bisect.bisect_right(ts, t_s, lo)
            if ts[i - 1] == t_s:
                return self._samples[i - 1].q_W_B_xyzw
            t0, t1 = ts[i - 1], ts[i]
            q0, q1 = self._samples[i - 1].q_W_B_xyzw, self._samples[i].q_W_B_xyzw
        if t1 - t0 > self.max_gap_s:
            return None
        return quat_slerp(q0, q1, (t_s - t0) / (t1 - t0))

    def _body_quats_between(self, t0_s: float, t1_s: float) -> tuple[list[float], np.ndarray]:
        """Stamps (N,) and q_W_B xyzw (N, 4) of the samples stamped in [t0, t1]."""
        with self._lock:
            lo = max(0, len(self._t_s) - self.capacity)
            i0 = bisect.bisect_left(self._t_s, t0_s, lo)
            i1 = bisect.bisect_right(self._t_s, t1_s, lo)
            ts = self._t_s[i0:i1]
            qs = [s.q_W_B_xyzw for s in self._samples[i0:i1]]
        return ts, np.asarray(qs, dtype=np.float64).reshape(-1, 4)

    def newest(self) -> AttitudeSample | None:
        with self._lock:
            return self._samples[-1] if self._samples else None

    def samples_after(self, t_ns: int | None) -> list[AttitudeSample]:
        """Buffered samples stamped after `t_ns` (all when None), oldest first."""
        with self._lock:
            lo = max(0, len(self._samples) - self.capacity)
            if t_ns is None:
                return self._samples[lo:]
            i = bisect.bisect_right(self._t_s, t_ns * 1e-9, lo)
            while i > lo and self._samples[i - 1].t_ns > t_ns:  # float rounding of ns stamps
                i -= 1
            while i < len(self._samples) and self._samples[i].t_ns <= t_ns:
                i += 1
            return self._samples[i:]

    def wait_covered(self, t_s: float, timeout_s: float) -> bool:
        """Block until a sample stamped at or after `t_s` is in (the AHRS has
        caught up with a capture time); False on timeout."""
        with self._new:
            return self._new.wait_for(lambda: bool(self._t_s) and self._t_s[-1] >= t_s,
                                      timeout_s)

    def wait_for_samples(self, count: int, timeout_s: float) -> bool:
        """Block until `count` samples have been pushed in total (tests, start-up)."""
        with self._new:
            return self._new.wait_for(lambda: self._stats.pushed >= count, timeout_s)

    @property
    def stats(self) -> BufferStats:
        with self._lock:
            return self._stats

    def __len__(self) -> int:
        with self._lock:
            return min(len(self._samples), self.capacity)


def _bump(stats: BufferStats, **deltas: int) -> BufferStats:
    return BufferStats(**{k: getattr(stats, k) + deltas.get(k, 0)
                          for k in stats.__dataclass_fields__})
