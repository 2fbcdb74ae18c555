"""The fused tracker's estimator: a Kalman filter on position and velocity in
the world W, the attitude taken from the AHRS, with one cloned anchor
position per tracker (stochastic cloning, Roumeliotis & Burdick, ICRA 2002).

State x = [p, v, a_1 .. a_n] (3 each). With the attitude given, translation
is linear, so the filter is exact (the error state is the state):

  predict    p += v dt, v += w, w ~ N(0, q dt) (white acceleration, the
             discretised constant-velocity model: Q = q [dt^3/3, dt^2/2;
             dt^2/2, dt]); anchors do not move;
  measure    tracker i's motion since its anchor, rotated into W:
             z_i = p - a_i + e_i, e_i ~ N(0, R_i);
  re-anchor  a_i := p, copying p's row and column of the covariance, so the
             anchor carries p's error (and its correlation with everything
             else): motion measured afterwards is relative to a position known
             only as well as p was. Drift accumulates exactly there.

  drift      a_i's covariance grows by Q (`diffuse`) when tracker i makes a
             new key: the tracker's world itself drifts there.

A tracker matches its frames against a key (NI-SLAM) or a local map of
landmarks (FastORB), so its error is about constant while it uses one key and
steps when it makes a new one, from the pose it made it at; back on an old key
(NI-SLAM's key re-use, FastORB's landmarks seen again) the error is what it
was. Modelling that drift on the anchor, rather than re-anchoring at each key,
keeps each tracker's own consistency: a tracker returning to an old key
measures the position it had there, and the filter uses that.
"""

from __future__ import annotations

import numpy as np


class AnchoredFilter:
    """Position/velocity Kalman filter with `n_anchors` cloned anchors."""

    def __init__(self, n_anchors: int, accel_sd_m_s2: float) -> None:
        self.n = 6 + 3 * n_anchors
        self.x = np.zeros(self.n)
        self.P = np.zeros((self.n, self.n))
        self.q = accel_sd_m_s2**2
        self.t_s: float | None = None

    # ------------------------------------------------------------ state
    @property
    def p(self) -> np.ndarray:
        return self.x[:3].copy()

    @property
    def P_pp(self) -> np.ndarray:
        return self.P[:3, :3].copy()

    def start(self, t_s: float, p: np.ndarray, var_p: float, speed_sd: float) -> None:
        """Position `p` at `t_s`, velocity unknown (zero mean, `speed_sd`);
        every anchor at `p`."""
        self.t_s = t_s
        self.x[:] = 0.0
        self.P[:] = 0.0
        self.x[:3] = p
        self.P[:3, :3] = np.eye(3) * var_p
        self.P[3:6, 3:6] = np.eye(3) * speed_sd**2
        for i in range((self.n - 6) // 3):
            self.anchor(i)

    def _sl(self, i: int) -> slice:
        return slice(6 + 3 * i, 9 + 3 * i)

    # ------------------------------------------------------------ steps
    def predict(self, t_s: float) -> None:
        assert self.t_s is not None
        dt = t_s - self.t_s
        if dt <= 0.0:
            return
        self.t_s = t_s
        F = np.eye(6)
        F[:3, 3:6] = np.eye(3) * dt
        self.x[:6] = F @ self.x[:6]
        P = self.P
        P[:6, :] = F @ P[:6, :]
        P[:, :6] = P[:, :6] @ F.T
        q = self.q
        P[:3, :3] += np.eye(3) * q * dt**3 / 3.0
        P[:3, 3:6] += np.eye(3) * q * dt**2 / 2.0
        P[3:6, :3] += np.eye(3) * q * dt**2 / 2.0
        P[3:6, 3:6] += np.eye(3) * q * dt

    def innovation(self, i: int, z: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(y, S) of measurement z_i = p - a_i: residual and its covariance."""
        s = self._sl(i)
        y = z - (self.x[:3] - self.x[s])
        P = self.P
        S = P[:3, :3] - P[:3, s] - P[s, :3] + P[s, s] + R
        return y, S

    def nis(self, i: int, z: np.ndarray, R: np.ndarray) -> float:
        """Squared Mahalanobis distance of z_i to the prediction (chi-square, 3 dof)."""
        y, S = self.innovation(i, z, R)
        return float(y @ np.linalg.solve(S, y))

    def update(self, i: int, z: np.ndarray, R: np.ndarray) -> None:
        """Kalman update with z_i = p - a_i (Joseph form: keeps P symmetric
        and positive over long runs)."""
        s = self._sl(i)
        y, S = self.innovation(i, z, R)
        PHt = self.P[:, :3] - self.P[:, s]  # P H^T with H = [I 0 .. -I ..]
        K = np.linalg.solve(S, PHt.T).T
        self.x += K @ y
        # Joseph: (I - K H) P (I - K H)^T + K R K^T
        IKH = np.eye(self.n)
        IKH[:, :3] -= K
        IKH[:, s] += K
        self.P = IKH @ self.P @ IKH.T + K @ R @ K.T

    def diffuse(self, i: int, Q: np.ndarray) -> None:
        """The tracker's world drifted by an unknown step of covariance Q
        relative to its anchor (it made a new key from a pose with that error)."""
        s = self._sl(i)
        self.P[s, s] += Q

    def anchor(self, i: int) -> None:
        """a_i := p (a clone: the anchor shares p's error)."""
        s = self._sl(i)
        self.x[s] = self.x[:3]
        self.P[s, :] = self.P[:3, :]
        self.P[:, s] = self.P[:, :3]
        self.P[s, s] = self.P[:3, :3]
