"""SE(3) helpers and the uniform-acceleration motion model of FastORB-SLAM.

Poses here are T_cw (4x4, world -> camera), the paper's and OpenCV's
convention: `solvePnP` returns them and Eq. 16 projects with them. Equation
numbers refer to Fu et al., "Fast ORB-SLAM without Keypoint Descriptors"
(IEEE TIP 2022).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence

import numpy as np

from onboard.core.se3 import inverse, se3_power


def predict_uam(
    times_s: Sequence[float], poses_cw: Sequence[np.ndarray], t_s: float, accel_gain: float = 1.0
) -> np.ndarray:
    """Predicted T_cw at `t_s` from the last (up to) three poses, oldest first.

    Three poses: the uniform-acceleration model. With equal frame intervals it
    is Eq. 14, T_pred_rel = T^{c-2}_{c-1} (T^{c-3}_{c-2})^-1 T^{c-2}_{c-1},
    then Eq. 15, T*_cw = T_pred_rel T_{c-1}. Unequal intervals (dropped
    frames) scale each relative motion in time, in units of the last interval:
    the mean velocity over an interval is the velocity at its midpoint, so the
    prediction stays exact for a constant acceleration. Two poses: constant
    velocity; one pose: no motion. `accel_gain` scales the acceleration
    term (1: the paper's model, 0: constant velocity).
    """
    if len(poses_cw) == 0:
        raise ValueError("predict_uam needs at least one pose")
    last = poses_cw[-1]
    if len(poses_cw) == 1:
        return last.copy()
    dt2 = times_s[-1] - times_s[-2]
    if not dt2 > 0.0:
        return last.copy()
    u = (t_s - times_s[-1]) / dt2  # the step to predict, in units of the last interval
    d2 = poses_cw[-1] @ inverse(poses_cw[-2])  # T^{c-2}_{c-1}: motion over the last interval
    if len(poses_cw) == 2 or accel_gain == 0.0:
        return se3_power(d2, u) @ last
    dt1 = times_s[-2] - times_s[-3]
    if not dt1 > 0.0:
        return se3_power(d2, u) @ last
    u1 = dt1 / dt2
    d1 = poses_cw[-2] @ inverse(poses_cw[-3])  # T^{c-3}_{c-2}
    v1 = se3_power(d1, 1.0 / u1)  # that motion per last-interval unit
    accel = se3_power(d2 @ inverse(v1), accel_gain * 2.0 / (u1 + 1.0))  # Eq. 13: velocity increment per unit
    v_next = se3_power(accel, 0.5 * (1.0 + u)) @ d2  # Eq. 14 when u1 = u = 1
    return se3_power(v_next, u) @ last  # Eq. 15


def project(
    K: np.ndarray, T_cw: np.ndarray, xyz_W: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 16: pixels (N, 2) of world points under T_cw, and the camera-frame
    depth (N,) (<= 0 behind the camera; those pixels are meaningless)."""
    p_C = xyz_W @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = p_C[:, 2]
    zs = np.where(z > 1e-6, z, 1.0)
    uv = np.empty((len(xyz_W), 2))
    uv[:, 0] = K[0, 0] * p_C[:, 0] / zs + K[0, 2]
    uv[:, 1] = K[1, 1] * p_C[:, 1] / zs + K[1, 2]
    return uv, z


def back_project(
    K: np.ndarray, T_cw: np.ndarray, uv: np.ndarray, z: np.ndarray
) -> np.ndarray:
    """World points (N, 3) of pixels `uv` at camera depths `z`."""
    x = (uv[:, 0] - K[0, 2]) / K[0, 0] * z
    y = (uv[:, 1] - K[1, 2]) / K[1, 1] * z
    p_C = np.stack([x, y, z], axis=1)
    R = T_cw[:3, :3]
    return (p_C - T_cw[:3, 3]) @ R  # R^T (p_C - t), row-wise


class FrameClock:
    """Frame times for the motion model with the stamp jitter taken out.

    Driver stamps of a 30 Hz camera wander by several ms around the true
    period (tum_fr1_rpy: 28-40 ms for a 32 ms period), and the UAM prediction
    would extrapolate that noise. The clock counts whole frame periods
    instead, the period being the median of recent intervals, so a dropped
    frame still counts as two steps; Eq. 14's fixed delta-t is the special case
    of no drops.
    """

    def __init__(self, window: int = 31):
        self._intervals: deque[float] = deque(maxlen=window)
        self._last_stamp: float | None = None
        self._last_time = 0.0

    @property
    def period(self) -> float:
        """The frame period [s] (1 until two frames have been seen)."""
        return float(np.median(self._intervals)) if self._intervals else 1.0

    def __call__(self, t_s: float) -> float:
        """The regularised time of the frame stamped `t_s` (call once per frame)."""
        if self._last_stamp is None:
            self._last_stamp = t_s
            return self._last_time
        dt = t_s - self._last_stamp
        if dt > 0:
            self._intervals.append(dt)
            period = float(np.median(self._intervals))
            self._last_time += max(1, round(dt / period)) * period
        self._last_stamp = t_s
        return self._last_time

