"""The fused tracker's estimator: a Kalman filter on position and velocity in
the world W, the attitude taken from the AHRS, with cloned anchor
positions (each tracker's last frame and its keys) (stochastic cloning, Roumeliotis & Burdick, ICRA 2002).

State x = [p, v, a_1 .. a_n] (3 each). With the attitude given, translation
is linear, so the filter is exact (the error state is the state):

  predict    p += v dt, v += w, w ~ N(0, q dt) (white acceleration, the
             discretised constant-velocity model: Q = q [dt^3/3, dt^2/2;
             dt^2/2, dt]); anchors do not move;
  measure    tracker i's motion since its anchor, rotated into W:
             z_i = p - a_i + e_i, e_i ~ N(0, R_i);
  clone      a_i := p, copying p's row and column of the covariance, so the
             anchor carries p's error (and its correlation with everything
             else): motion measured afterwards is relative to a position known
             only as well as p was. Drift accumulates exactly there.

A tracker matches its frames against a key (NI-SLAM) or a local map of
landmarks (FastORB): its error is about constant while it uses one key and
steps when it makes a new one, from the pose it made it at. So each
measurement is taken against a clone of the fused position where the
tracker's reference was made (onboard.fusion.fused): the drift then is the
fused error at those points, carried in P with its correlations, and a
tracker coming back to an old key closes the loop against that key's clone.

Frozen copies (Schmidt's "consider" states), `n_frozen` slots: a position
put out at frame j is a fixed number whose error e_j never changes, unlike a
clone, whose estimate later updates correct. Its cross-covariance with the
state, C_j = Cov(x, e_j) (n x 3), follows the state's error: predict
C_j := F C_j (no noise: w is independent of e_j), update C_j := (I - K H) C_j
(the state's gain; the frozen value takes none), a clone's rows copied with
it. Var(e_j) stays what P_pp was at j. Kept outside P (all slots side by side
in one n x 3m array, one product per step), so the filter's own numbers do
not change (onboard.fusion.displacement: the velocity's covariance).
"""

from __future__ import annotations

import numpy as np


class AnchoredFilter:
    """Position/velocity Kalman filter with `n_anchors` cloned anchors."""

    def __init__(self, n_anchors: int, accel_sd_m_s2: float, n_frozen: int = 0) -> None:
        self.n = 6 + 3 * n_anchors
        self.x = np.zeros(self.n)
        self.P = np.zeros((self.n, self.n))
        self.q = accel_sd_m_s2**2
        self.t_s: float | None = None
        self.C = np.zeros((self.n, 3 * n_frozen))  # [C_0 .. C_m-1], C_j = Cov(x, e_j)
        self.V = np.zeros((n_frozen, 3, 3))  # Var(e_j)
        self.epoch = 0  # + 1 at each start: the frozen copies of before are void

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
        self.epoch += 1
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
        self.x[:3] += dt * self.x[3:6]
        P = self.P  # F P F^T with F = [I dt I; 0 I] on p, v: two row and two column operations
        P[:3, :] += dt * P[3:6, :]
        P[:, :3] += dt * P[:, 3:6]
        q = self.q
        P[:3, :3] += np.eye(3) * q * dt**3 / 3.0
        P[:3, 3:6] += np.eye(3) * q * dt**2 / 2.0
        P[3:6, :3] += np.eye(3) * q * dt**2 / 2.0
        P[3:6, 3:6] += np.eye(3) * q * dt
        self.C[:3] += dt * self.C[3:6]

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
        """Kalman update with z_i = p - a_i. H has two identity blocks, so
        P H^T is two column blocks and the update costs O(n^2), not O(n^3):
        P -= K (P H^T)^T, then symmetrised (the state holds up to a hundred
        numbers with the key clones; the Joseph form's n^3 products cost
        milliseconds)."""
        s = self._sl(i)
        y, S = self.innovation(i, z, R)
        PHt = self.P[:, :3] - self.P[:, s]  # P H^T with H = [I 0 .. -I ..]
        K = np.linalg.solve(S, PHt.T).T
        self.C -= K @ (self.C[:3] - self.C[s])  # (I - K H) C
        self.x += K @ y
        self.P -= K @ PHt.T
        self.P = 0.5 * (self.P + self.P.T)

    def anchor(self, i: int) -> None:
        """a_i := p (a clone: the anchor shares p's error)."""
        self._clone(slice(0, 3), self._sl(i))

    def copy(self, src: int, dst: int) -> None:
        """a_dst := a_src (the same clone in another slot)."""
        self._clone(self._sl(src), self._sl(dst))

    def widen(self, i: int, Q: np.ndarray) -> None:
        """a_i += an independent error of covariance Q (one that every
        measurement against this anchor shares, e.g. its key's attitude error)."""
        s = self._sl(i)
        self.P[s, s] += Q

    def forget(self, i: int) -> None:
        """Slot i no longer used: no state, no correlation."""
        s = self._sl(i)
        self.x[s] = 0.0
        self.P[s, :] = 0.0
        self.P[:, s] = 0.0
        self.C[s] = 0.0

    def freeze(self, j: int) -> None:
        """Keep p as put out now in frozen slot j (module doc)."""
        self.C[:, 3 * j:3 * j + 3] = self.P[:, :3]
        self.V[j] = self.P[:3, :3]

    def displacement_cov(self, j: int) -> np.ndarray:
        """Cov(p - p_j) for the frozen copy p_j in slot j:
        P_pp - C_p - C_p^T + Var(e_j), C_p = Cov(p, e_j) (C_j's rows of p)."""
        Cp = self.C[:3, 3 * j:3 * j + 3]
        D = self.P[:3, :3] - Cp - Cp.T + self.V[j]
        return 0.5 * (D + D.T)

    def _clone(self, src: slice, dst: slice) -> None:
        self.x[dst] = self.x[src]
        self.P[dst, :] = self.P[src, :]
        self.P[:, dst] = self.P[:, src]
        self.P[dst, dst] = self.P[src, src]
        self.C[dst] = self.C[src]
