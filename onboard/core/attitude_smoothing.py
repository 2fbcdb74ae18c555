"""The attitude at a frame fitted to the AHRS samples around it, not slerped
between the two next to it (docs/nislam-error-budget.md, "AHRS jitter").

An AHRS samples the attitude 3x faster than the camera (100 Hz against
30 Hz) and each sample carries its own jitter (the myAHRS+ class: ~0.1 deg
per sample), which NI-SLAM turns into a lateral shift of angle x depth
(Eqs. 9-12: the cloud is rotated by the attitude before the projection). A
quadratic fitted by least squares to the samples within +-`half_s`, in the
tangent space at the slerped attitude, keeps the motion (exact for constant
angular acceleration; a jerk, odd about the frame, does not move the centre)
and averages the jitter: over +-40 ms at 100 Hz (9 samples) its sd at the
centre is 0.51 of one sample's. The window is a low-pass filter (a
Savitzky-Golay filter of order 2): +-40 ms passes the rotation up to 12 Hz
(-3 dB; 99 % at 5 Hz), above a multirotor's attitude-control bandwidth
(5-10 Hz), so the vehicle's own motion goes through and the sensor's jitter
does not (+-30 ms: 16 Hz, sd 0.58; +-50 ms: 10 Hz, sd 0.46).

Only where the samples are dense enough to average: at least 2 on each side
and 5 in all; else (an attitude sampled at the frame times, as the TUM
replays give it; around an outage; live, the newest samples not in yet) the
slerp between the two neighbours. Live, the samples after the frame that
have arrived when it is tracked are used (the fit then leans on the earlier
side); nothing waits for more.
"""

from __future__ import annotations

import cv2
import numpy as np

DEFAULT_HALF_S = 0.04
MIN_SAMPLES = 5
MIN_EACH_SIDE = 2


def dense_enough(tau_s: np.ndarray) -> bool:
    """Samples at `tau_s` (s from the frame): enough to average, not interpolate."""
    return (len(tau_s) >= MIN_SAMPLES and np.count_nonzero(tau_s < 0) >= MIN_EACH_SIDE
            and np.count_nonzero(tau_s > 0) >= MIN_EACH_SIDE)


def _rotvecs(q0: np.ndarray, q: np.ndarray) -> np.ndarray:
    """log(q0^-1 q_i) (N, 3) for unit quaternions xyzw (the shorter way)."""
    x0, y0, z0, w0 = -q0[0], -q0[1], -q0[2], q0[3]  # q0's conjugate
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    rel = np.stack([
        w0 * x + x0 * w + y0 * z - z0 * y,
        w0 * y - x0 * z + y0 * w + z0 * x,
        w0 * z + x0 * y - y0 * x + z0 * w,
        w0 * w - x0 * x - y0 * y - z0 * z,
    ], axis=1)
    rel[rel[:, 3] < 0] *= -1.0
    s = np.linalg.norm(rel[:, :3], axis=1)
    scale = np.where(s > 1e-12, 2.0 * np.arctan2(s, rel[:, 3]) / np.maximum(s, 1e-300), 2.0)
    return rel[:, :3] * scale[:, None]


def fitted_delta(tau_s: np.ndarray, q_slerp: np.ndarray, qs: np.ndarray) -> np.ndarray:
    """The fitted attitude at tau = 0 as a rotation from `q_slerp` (the
    slerped attitude there, xyzw): 3x3, applied on the right."""
    a = np.stack([np.ones_like(tau_s), tau_s, tau_s * tau_s], axis=1)
    coef = np.linalg.solve(a.T @ a, a.T @ _rotvecs(q_slerp, qs))  # normal equations, 3 x 3
    delta, _ = cv2.Rodrigues(coef[0].reshape(3, 1))
    return delta
