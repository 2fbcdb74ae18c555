"""What goes on the wire to zenoh, built from our types: the `pose` JSON
object (fields: zenoh_out.py's docstring), the quality convention, and the
map thread's rate limit. Pure; zenoh_out.py owns the session and threads."""

from __future__ import annotations

import math
from typing import Any

from scipy.spatial.transform import Rotation

from onboard.core.messages import TrackResult, TrackState


def tracking_quality(result: TrackResult) -> int:
    """-1 lost, 0 starting, 1-100 tracking (ODOMETRY's convention)."""
    if result.trusted:
        return int(min(100, max(1, result.quality)))
    return -1 if result.state is TrackState.LOST else 0


def finite_or_none(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def pose_message(result: TrackResult, seq: int) -> dict[str, Any]:
    """The JSON object published on `pose` for one result."""
    trusted = result.trusted and result.p_W_m is not None and result.R_W_C is not None
    q = Rotation.from_matrix(result.R_W_C).as_quat(canonical=True) if trusted else None
    return {
        "seq": seq,
        "t_s": float(result.t_s),
        "state": result.state.value,
        "trusted": trusted,
        "p_W_m": [float(v) for v in result.p_W_m] if trusted else None,
        "q_W_C_xyzw": [float(v) for v in q] if q is not None else None,
        "pose_var": [finite_or_none(v) for v in result.pose_var] if trusted else None,
        "quality": tracking_quality(result),
        "psr": finite_or_none(result.psr),
        "keyframe_id": int(result.keyframe_id),
        "reset_counter": int(result.reset_counter),
        "lost_reason": result.lost_reason,
    }


class RateLimit:
    """Average rate limit with a one-second allowance: `delay_s(n)` is how long
    to wait before sending n bytes (0 without a limit)."""

    def __init__(self, bytes_per_s: float, burst_s: float = 1.0) -> None:
        self.rate = bytes_per_s
        self.burst_s = burst_s
        self._next_free = -math.inf

    def delay_s(self, n_bytes: int, now: float) -> float:
        if self.rate <= 0:
            return 0.0
        # Virtual finish time of everything sent: after a quiet spell it may
        # lag `now` by burst_s, so up to burst_s x rate bytes go at once.
        self._next_free = max(self._next_free, now - self.burst_s) + n_bytes / self.rate
        return max(0.0, self._next_free - now)
