"""Rigid transforms (SE(3)) as 4x4 matrices: composition helpers, OpenCV's
(rvec, tvec), and the exponential and logarithm maps.

Poses named T_cw map world points into the camera (the convention of OpenCV
and FastORB-SLAM); `camera_in_world` gives the camera's position and axes.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from onboard.core.rotations import so3_log


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from a rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (R^T, -R^T t), exact and cheap."""
    R = T[:3, :3]
    return make_pose(R.T, -R.T @ T[:3, 3])


def pose_from_rvec(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """T_cw from OpenCV's (rvec, tvec)."""
    R, _ = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))
    return make_pose(R, np.asarray(tvec, np.float64).ravel())


def rvec_tvec(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's (rvec, tvec), both (3, 1) float64, of T_cw."""
    rvec, _ = cv2.Rodrigues(np.ascontiguousarray(T[:3, :3]))
    return rvec, T[:3, 3].reshape(3, 1).copy()


def camera_in_world(T_cw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(p_W_m, R_W_C) of the camera with pose T_cw."""
    R_W_C = T_cw[:3, :3].T
    return -R_W_C @ T_cw[:3, 3], R_W_C.copy()


def _skew(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def se3_log(T: np.ndarray) -> np.ndarray:
    """Twist xi = (phi, rho) of Eq. 3 with T = exp(xi^), phi the rotation vector."""
    phi = so3_log(T[:3, :3])
    return np.concatenate([phi, _v_inverse(phi) @ T[:3, 3]])


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """exp(xi^) of a twist (phi, rho) (Eqs. 2-3)."""
    phi, rho = xi[:3], xi[3:]
    R, _ = cv2.Rodrigues(np.asarray(phi, np.float64).reshape(3, 1))
    return make_pose(R, _v_matrix(phi) @ rho)


def se3_power(T: np.ndarray, s: float) -> np.ndarray:
    """T^s = exp(s log T): the same screw motion scaled in time."""
    if s == 1.0:
        return T
    return se3_exp(s * se3_log(T))


def _v_matrix(phi: np.ndarray) -> np.ndarray:
    """Left Jacobian V of SO(3): translation part of the SE(3) exponential."""
    a = math.sqrt(float(phi @ phi))
    K = _skew(phi)
    if a < 1e-6:
        return np.eye(3) + 0.5 * K + K @ K / 6.0
    return (
        np.eye(3)
        + (1.0 - math.cos(a)) / a**2 * K
        + (a - math.sin(a)) / a**3 * (K @ K)
    )


def _v_inverse(phi: np.ndarray) -> np.ndarray:
    a = math.sqrt(float(phi @ phi))
    K = _skew(phi)
    if a < 1e-6:
        return np.eye(3) - 0.5 * K + K @ K / 12.0
    half = 0.5 * a
    return np.eye(3) - 0.5 * K + (1.0 - half / math.tan(half)) / a**2 * (K @ K)
