"""The attitude at a frame fitted to the AHRS samples around it, not slerped
between the two next to it (docs/nislam-error-budget.md, "AHRS jitter").

An AHRS samples the attitude 3x faster than the camera (100 Hz against
30 Hz) and each sample carries its own jitter (the myAHRS+ class: ~0.1 deg
per sample), which NI-SLAM turns into a lateral shift of angle x depth
(Sec. IV-A: the cloud is rotated by the attitude before the projection). A
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

import bisect

import numpy as np

DEFAULT_HALF_S = 0.04
MIN_SAMPLES = 5
MIN_EACH_SIDE = 2


def local_fit(t_s: float, ts: list[float], qs: np.ndarray, q_slerp) -> np.ndarray | None:
    """The fitted attitude at `t_s` as a rotation from `q_slerp` (3x3, on the
    right), from the samples (increasing stamps `ts`, quaternions `qs` (N, 4)
    xyzw) within the window; None where they are too sparse to average."""
    n_before = bisect.bisect_left(ts, t_s)
    n_after = len(ts) - bisect.bisect_right(ts, t_s)
    if len(ts) < MIN_SAMPLES or n_before < MIN_EACH_SIDE or n_after < MIN_EACH_SIDE:
        return None
    return fitted_delta(np.asarray(ts, dtype=np.float64) - t_s, np.asarray(q_slerp), qs)


def _fitted_delta_py(tau_s: np.ndarray, q0: np.ndarray, qs: np.ndarray) -> np.ndarray:
    """One pass: rotation vectors log(q0^-1 q_i) (the shorter way), the
    normal equations of the quadratic in tau, its value at 0 as a rotation
    (Rodrigues). About 2 us for 9 samples, against ~150 us in numpy."""
    x0, y0, z0, w0 = -q0[0], -q0[1], -q0[2], q0[3]  # q0's conjugate
    ata = np.zeros((3, 3))
    atv = np.zeros((3, 3))
    for i in range(len(tau_s)):
        x, y, z, w = qs[i, 0], qs[i, 1], qs[i, 2], qs[i, 3]
        rx = w0 * x + x0 * w + y0 * z - z0 * y
        ry = w0 * y - x0 * z + y0 * w + z0 * x
        rz = w0 * z + x0 * y - y0 * x + z0 * w
        rw = w0 * w - x0 * x - y0 * y - z0 * z
        if rw < 0.0:
            rx, ry, rz, rw = -rx, -ry, -rz, -rw
        sn = np.sqrt(rx * rx + ry * ry + rz * rz)
        k = 2.0 * np.arctan2(sn, rw) / sn if sn > 1e-12 else 2.0
        t = tau_s[i]
        basis = (1.0, t, t * t)
        v = (rx * k, ry * k, rz * k)
        for a in range(3):
            for b in range(3):
                ata[a, b] += basis[a] * basis[b]
                atv[a, b] += basis[a] * v[b]
    d = np.linalg.solve(ata, atv)[0]  # the quadratic's value at tau = 0
    theta = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    kx = np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
    if theta < 1e-12:
        return np.eye(3) + kx
    return (np.eye(3) + np.sin(theta) / theta * kx
            + (1.0 - np.cos(theta)) / (theta * theta) * (kx @ kx))


_compiled = None


def _fitted_delta():
    """The kernel compiled on first use (numba's disk cache after the first
    process): importing the attitude buffer, e.g. to load a configuration,
    costs no numba import."""
    global _compiled
    if _compiled is None:
        from numba import njit
        _compiled = njit(cache=True, nogil=True)(_fitted_delta_py)
    return _compiled


def fitted_delta(tau_s: np.ndarray, q_slerp: np.ndarray, qs: np.ndarray) -> np.ndarray:
    """The fitted attitude at tau = 0 as a rotation from `q_slerp` (the
    slerped attitude there, xyzw; `qs` (N, 4) the samples at `tau_s`):
    3x3, applied on the right."""
    return _fitted_delta()(np.ascontiguousarray(tau_s, dtype=np.float64),
                         np.ascontiguousarray(q_slerp, dtype=np.float64),
                         np.ascontiguousarray(qs, dtype=np.float64))


def warm_up() -> None:
    """Compile (or load from numba's disk cache) before the first frame."""
    q = np.array([[0.0, 0.0, 0.0, 1.0]] * 5)
    fitted_delta(np.linspace(-0.02, 0.02, 5), q[0], q)
