"""Rolling shutter for FastORB: pixels and back-projected points brought to
the instant of the image's middle row.

A rolling-shutter colour camera (the Kinect of the TUM sequences, the
OAK-D's IMX378) reads its rows out one after another over `readout_s`, so a
pixel in row v was seen at t_mid + tau_v, tau_v = readout (v / H - 1/2) (top
row first). The pose PnP fits is one rigid T_cw for the whole image; under a
turn the rows are sheared against it (65 deg/s and 28 ms: 0.5 deg, about
5 px, from top to bottom), which RANSAC and the inlier gate answer by
dropping the top and bottom rows and the refinement by tilting the pose.
Landmarks made from such a frame carry the shear into the map.

With the camera's twist xi = (phi, rho) per second (left perturbation:
T_cw(t_mid + tau) = exp(tau xi^) T_cw(t_mid)), a point seen in row v at
camera coordinates p_v sits at p_mid = exp(-tau_v xi^) p_v, to first order
p_v - tau_v (phi x p_v + rho) (as NI-SLAM's shutter correction,
onboard/nislam/shutter.py, there with the AHRS rate). FastORB reads no
attitude while tracking, so the twist comes from its own motion model.
Pure: arrays in, arrays out.
"""

from __future__ import annotations

import numpy as np

from onboard.core.se3 import inverse, se3_exp, se3_log
from onboard.fastorb.refine_kernels import refine_rate_loop


def twist_rate(T_from: np.ndarray, T_to: np.ndarray, dt_s: float) -> np.ndarray:
    """(6,) twist (phi, rho) per second taking T_from to T_to (both T_cw)
    over dt_s: T_to = exp(dt xi^) T_from. Zeros when dt_s is not positive."""
    if not dt_s > 0.0:
        return np.zeros(6)
    return se3_log(T_to @ inverse(T_from)) / dt_s


def row_times(v: np.ndarray, readout_s: float, height_px: int) -> np.ndarray:
    """tau (N,) [s] of pixel rows `v` after the middle row's instant."""
    return readout_s * (np.asarray(v, np.float64) / height_px - 0.5)


def back_project(uv: np.ndarray, z: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera points (N, 3) of pixels `uv` (float64) at depths `z`."""
    p = np.empty((len(uv), 3))
    p[:, 0] = (uv[:, 0] - K[0, 2]) / K[0, 0] * z
    p[:, 1] = (uv[:, 1] - K[1, 2]) / K[1, 1] * z
    p[:, 2] = z
    return p


def points_at_mid(
    uv: np.ndarray, z: np.ndarray, K: np.ndarray, xi: np.ndarray, readout_s: float,
    height_px: int,
) -> np.ndarray:
    """Camera points (N, 3) of pixels `uv` at depths `z`, each moved from its
    row's instant to the middle row's: p_v - tau_v (phi x p_v + rho)."""
    uv = np.asarray(uv, np.float64)
    p = back_project(uv, np.asarray(z, np.float64), K)
    if readout_s == 0.0 or not np.any(xi):
        return p
    tau = row_times(uv[:, 1], readout_s, height_px)[:, None]
    w0, w1, w2 = xi[0], xi[1], xi[2]  # omega x p written out: np.cross's own products, less overhead
    cross = np.empty_like(p)
    cross[:, 0] = w1 * p[:, 2] - w2 * p[:, 1]
    cross[:, 1] = w2 * p[:, 0] - w0 * p[:, 2]
    cross[:, 2] = w0 * p[:, 1] - w1 * p[:, 0]
    return p - tau * (cross + xi[3:])


def pixels_at_mid(
    uv: np.ndarray, z: np.ndarray, K: np.ndarray, xi: np.ndarray, readout_s: float,
    height_px: int,
) -> np.ndarray:
    """Pixels (N, 2) where `uv` would have been seen at the middle row's
    instant; `z` (N,) is the point's depth (the translation's share of the
    shift needs it; a rough one will do: at 0.3 m/s and 15 ms, 4.5 mm of
    motion, 2 px at 1 m). `uv` unchanged without a readout or a motion."""
    uv = np.asarray(uv, np.float64)
    if readout_s == 0.0 or not np.any(xi) or len(uv) == 0:
        return uv
    p = points_at_mid(uv, np.maximum(z, 1e-3), K, xi, readout_s, height_px)
    iz = 1.0 / np.maximum(p[:, 2], 1e-6)
    return np.stack([K[0, 0] * p[:, 0] * iz + K[0, 2], K[1, 1] * p[:, 1] * iz + K[1, 2]], axis=1)


def refine_with_rate(
    T_cw: np.ndarray, obj: np.ndarray, uv: np.ndarray, disp: np.ndarray, K: np.ndarray,
    bf_px: float, huber_px: float, readout_s: float, height_px: int, xi_prior: np.ndarray,
    rate_sd: float, iterations: int = 5,
) -> tuple[np.ndarray, np.ndarray]:
    """(T_cw, omega): the pose and the body rate (rad/s, camera axes) that
    best explain the raw rolling-shutter pixels `uv` of landmarks `obj`
    (inliers only), with the disparity residual where `disp` > 0 and Huber
    weights, as pose.refine_pose. The rows' shear measures the rate: a point
    in row v is seen at p + tau_v (omega x p + rho), p = T_cw X, so its pixel
    moves by tau_v J_pi (-[p]x) per unit of omega. The motion model's rate
    (xi_prior[:3], sd `rate_sd` in px-equivalent units of 1 px per rad/s x
    rate_sd) keeps it where few rows are seen; the translation rate stays
    the motion model's (xi_prior[3:]): at 0.3 m/s it shears by about 2 px."""
    obj = np.ascontiguousarray(obj, np.float64)
    uv = np.ascontiguousarray(uv, np.float64)
    tau = row_times(uv[:, 1], readout_s, height_px)
    xi_prior = np.asarray(xi_prior, np.float64)
    try:  # the iterations compiled (refine_kernels.refine_rate_loop)
        return refine_rate_loop(np.ascontiguousarray(T_cw, np.float64), xi_prior[:3].copy(),
                                xi_prior[3:].copy(), xi_prior[:3].copy(), obj, uv,
                                np.ascontiguousarray(disp, np.float64), tau, K[0, 0], K[1, 1],
                                K[0, 2], K[1, 2], float(bf_px), float(huber_px), float(rate_sd),
                                int(iterations))
    except np.linalg.LinAlgError:  # a zero pivot the pre-check missed
        return _refine_with_rate_numpy(T_cw, obj, uv, disp, K, bf_px, huber_px, readout_s,
                                       height_px, xi_prior, rate_sd, iterations)


def _refine_with_rate_numpy(
    T_cw: np.ndarray, obj: np.ndarray, uv: np.ndarray, disp: np.ndarray, K: np.ndarray,
    bf_px: float, huber_px: float, readout_s: float, height_px: int, xi_prior: np.ndarray,
    rate_sd: float, iterations: int = 5,
) -> tuple[np.ndarray, np.ndarray]:
    """refine_with_rate in numpy (the compiled loop's reference)."""
    obj = np.asarray(obj, np.float64)
    uv = np.asarray(uv, np.float64)
    tau = row_times(uv[:, 1], readout_s, height_px)
    rho = xi_prior[3:]
    omega = xi_prior[:3].copy()
    fx, fy = K[0, 0], K[1, 1]
    has = (disp > 0) & (bf_px > 0)
    for _ in range(iterations):
        p = obj @ T_cw[:3, :3].T + T_cw[:3, 3]
        wx, wy, wz = omega
        cross = np.stack([wy * p[:, 2] - wz * p[:, 1], wz * p[:, 0] - wx * p[:, 2],
                          wx * p[:, 1] - wy * p[:, 0]], axis=1)  # omega x p
        q = p + tau[:, None] * (cross + rho)
        iz = 1.0 / np.maximum(q[:, 2], 1e-6)
        r = np.stack([fx * q[:, 0] * iz + K[0, 2] - uv[:, 0],
                      fy * q[:, 1] * iz + K[1, 2] - uv[:, 1],
                      np.where(has, bf_px * iz - disp, 0.0)], axis=1)
        # J_pi rows times -[p]x, written out: d(u, v, d)/d(phi) at q ~ p
        x, y, zz = p[:, 0], p[:, 1], p[:, 2]
        a, b, c = fx * iz, -fx * q[:, 0] * iz**2, fy * iz
        e, dd = -fy * q[:, 1] * iz**2, np.where(has, -bf_px * iz**2, 0.0)
        J = np.zeros((len(p), 3, 9))
        J[:, 0, 0], J[:, 0, 1], J[:, 0, 2] = b * y, a * zz - b * x, -a * y
        J[:, 1, 0], J[:, 1, 1], J[:, 1, 2] = -c * zz + e * y, -e * x, c * x
        J[:, 2, 0], J[:, 2, 1] = dd * y, -dd * x
        J[:, 0, 3], J[:, 0, 5] = a, b
        J[:, 1, 4], J[:, 1, 5] = c, e
        J[:, 2, 5] = dd
        J[:, :, 6:] = tau[:, None, None] * J[:, :, :3]
        norm = np.sqrt(np.sum(r * r, axis=1))
        w = np.where(norm <= huber_px, 1.0, huber_px / np.maximum(norm, 1e-12))
        Jf = J.reshape(-1, 9)
        Jw = Jf * np.repeat(w, 3)[:, None]
        H = Jw.T @ Jf
        g = Jw.T @ r.reshape(-1)
        H[6:, 6:] += np.eye(3) / rate_sd**2
        g[6:] += (omega - xi_prior[:3]) / rate_sd**2
        try:
            step = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        T_cw = se3_exp(step[:6]) @ T_cw
        omega = omega + step[6:]
        if float(np.abs(step).max()) < 1e-6:
            break
    return T_cw, omega
