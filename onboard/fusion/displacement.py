"""The covariance of the fused output's recent displacements, for the velocity
the MAVLink feed sends (onboard.outputs.mavlink_feed differences the pose
against the one up to `velocity_window_s` earlier).

The filter's position variance P_pp is absolute: it carries the drift of every
key since the start and grows over the flight, so (P_pp(k) + P_pp(j)) / dt^2
says less and less about a velocity whose displacement over 0.1 s is as
precise at minute 10 as at second 1. What the velocity needs is the
covariance of the displacement itself. Stochastic cloning (Roumeliotis &
Burdick, ICRA 2002) gives it exactly: after frame j's update its output
position is copied into a clone c_j (a_i := p in AnchoredFilter, P's row and
column copied, so c_j carries p_j's error and all its correlations); the
clone does not move in the prediction (F = I on it) and takes its share of
every later update through P, so at frame k

    Cov(p_k - c_j) = P_pp - P_pc - P_cp + P_cc

the drift both positions share (every key's error before j) cancels, and what
is left is the error of the motion measured between j and k. The fused
filter's own velocity state is no substitute: its sd comes from the
white-acceleration model (0.46-0.5 m/s at 5 m/s^2), ten times the error of
the differenced poses.

A ring of `velocity_clones` slots holds the outputs of the last frames; each
result reports the covariance against every held clone with that frame's
time (`TrackResult.displacement_cov`). A restart clears them: the feed starts
a new epoch there and sends no velocity across it.
"""

from __future__ import annotations

import numpy as np

from onboard.fusion.filter import AnchoredFilter


class OutputClones:
    """Clones of the last `n` outputs in filter slots `first` .. `first + n - 1`."""

    def __init__(self, first: int, n: int) -> None:
        self.slots = list(range(first, first + n))
        self.held: dict[int, float] = {}  # slot -> the t_s of the output cloned there
        self._next = 0

    def clear(self) -> None:
        self.held.clear()

    def covariances(self, f: AnchoredFilter) -> tuple[tuple[float, np.ndarray], ...]:
        """(t_j, Cov(p - c_j)) (3x3, W) for each held clone, oldest first."""
        P = f.P
        out = []
        for slot, t_j in sorted(self.held.items(), key=lambda item: item[1]):
            s = f._sl(slot)
            C = P[:3, :3] - P[:3, s] - P[s, :3] + P[s, s]
            out.append((t_j, 0.5 * (C + C.T)))
        return tuple(out)

    def record(self, f: AnchoredFilter, t_s: float) -> None:
        """Clone the output of frame `t_s` (after its updates) over the oldest."""
        if not self.slots:
            return
        slot = self.slots[self._next]
        self._next = (self._next + 1) % len(self.slots)
        f.anchor(slot)
        self.held[slot] = t_s
