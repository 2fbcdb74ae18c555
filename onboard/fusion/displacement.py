"""The covariance of the fused output's recent displacements, for the velocity
the MAVLink feed sends (onboard.outputs.mavlink_feed differences the pose
against the one up to `velocity_window_s` earlier).

The filter's position variance P_pp is absolute: it carries the drift of every
key since the start and grows over the flight, so (P_pp(k) + P_pp(j)) / dt^2
says less and less about a velocity whose displacement over 0.1 s is as
precise at minute 10 as at second 1. What the velocity needs is the
covariance of the displacement itself, p_k - p_j, with p_j the position put
out at frame j. The filter keeps it with a frozen copy of each output
(AnchoredFilter.freeze, `velocity_clones` slots: stochastic cloning, Roumeliotis & Burdick, ICRA 2002,
with the copy's estimate never corrected afterwards, as Schmidt's consider
states, since the feed differences the value it sent, not a smoothed one):

    Cov(p_k - p_j) = P_pp - C_p - C_p^T + Var(e_j),   C_p = Cov(e_p(k), e_j)

The drift both positions share (every key's error before j) cancels; what is
left is the error of the motion measured between j and k. The filter's own
velocity state is no substitute: its sd comes from the white-acceleration
model (0.46-0.5 m/s at 5 m/s^2), ten times the error of the differenced
poses.

The last `velocity_clones` outputs are held; each result reports the
covariance against each of them with that frame's time
(`TrackResult.displacement_cov`). A restart of the filter drops them: the
feed starts a new epoch there and sends no velocity across it.
"""

from __future__ import annotations

import numpy as np

from onboard.fusion.filter import AnchoredFilter


class OutputClones:
    """Which of a filter's frozen slots holds which output (a ring), by t_s."""

    def __init__(self) -> None:
        self.held: dict[int, tuple[float, int]] = {}  # slot -> (t_s, the filter's epoch)
        self._next = 0

    def covariances(self, f: AnchoredFilter) -> tuple[tuple[float, np.ndarray], ...]:
        """(t_j, Cov(p - p_j)) (3x3, W) for each output held, oldest first;
        none from before the filter's last start (the feed's new epoch)."""
        held = sorted((t, j) for j, (t, epoch) in self.held.items() if epoch == f.epoch)
        return tuple((t, f.displacement_cov(j)) for t, j in held)

    def record(self, f: AnchoredFilter, t_s: float) -> None:
        """Freeze the output of frame `t_s` (after its updates) over the oldest."""
        m = f.V.shape[0]
        if m == 0:
            return
        j, self._next = self._next, (self._next + 1) % m
        f.freeze(j)
        self.held[j] = (t_s, f.epoch)
