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

With the AHRS's white noise stated (`[nislam] attitude_sd_deg` live and
for a real AHRS's recording; a simulated flight's own figure; ground
truth none; plus what a replay adds: sim_replay.attitude.recorded_noise_deg)
the window widens beyond +-`half_s`, up to `[ahrs] smoothing_max_s`, as far as the fits of
the wider windows agree with the narrower ones within their noise
(`adaptive_fit`, the ICI rule): a noisy AHRS on a smooth flight is averaged
over up to 21 samples instead of 9, and where the motion bends the window
stays narrow. Without a stated noise nothing changes.
"""

from __future__ import annotations

import bisect
import math

import numpy as np

DEFAULT_HALF_S = 0.04
DEFAULT_MAX_HALF_S = 0.1  # the widest window adaptive_fit tries ([ahrs] smoothing_max_s)
MIN_SAMPLES = 5
MIN_EACH_SIDE = 2
ICI_GAMMA = 2.0  # adaptive_fit's intervals of +-2 sd: the usual choice (Katkovnik: 1.5-3)
LADDER_STEP = 1.5  # ... over windows each 1.5x the last
_ALL = np.array([np.inf])  # one window holding every sample (fitted_delta)


class Window:
    """An attitude source's local-fit window: +-`half_s`, widened up to
    +-`max_half_s` where the AHRS states its white noise (`adaptive_fit`).
    The live buffer and the replay's series each hold one."""

    def __init__(self, half_s: float, max_half_s: float = 0.0, noise_sd_deg: float = 0.0) -> None:
        self.half_s = float(half_s)
        self.widest_s = max(self.half_s, float(max_half_s))  # the samples a look-up needs
        self.noise_sd_rad = math.radians(noise_sd_deg)
        # half_s 0: the slerp alone (the sources never fit), nothing to widen
        self.widens = self.half_s > 0.0 and self.noise_sd_rad > 0.0 and self.widest_s > self.half_s
        self._halves = np.asarray(_ladder(self.half_s, self.widest_s) if self.widens else [self.half_s])

    def fit(self, t_s: float, ts: list[float], qs: np.ndarray, q_slerp,
            widen: bool = True) -> np.ndarray | None:
        """The attitude at `t_s` as a rotation from `q_slerp` (3x3, on the
        right), from the samples (increasing stamps `ts`, quaternions `qs`
        (N, 4) xyzw) within +-widest_s: the fit over +-half_s, or (`widen`
        and a stated noise) the widest window the data allow; None: the
        slerp stands."""
        if not (widen and self.widens):
            i0 = bisect.bisect_left(ts, t_s - self.half_s)
            i1 = bisect.bisect_right(ts, t_s + self.half_s)
            return local_fit(t_s, ts[i0:i1], qs[i0:i1], q_slerp)
        j = bisect.bisect_right(ts, t_s)
        w = 0.0 if j == 0 or j >= len(ts) or ts[j - 1] == t_s else (t_s - ts[j - 1]) / (ts[j] - ts[j - 1])
        return adaptive_fit(t_s, ts, qs, q_slerp, w, self._halves, self.noise_sd_rad)


def local_fit(t_s: float, ts: list[float], qs: np.ndarray, q_slerp) -> np.ndarray | None:
    """The fitted attitude at `t_s` as a rotation from `q_slerp` (3x3, on the
    right), from the samples (increasing stamps `ts`, quaternions `qs` (N, 4)
    xyzw) within the window; None where they are too sparse to average."""
    n_before = bisect.bisect_left(ts, t_s)
    n_after = len(ts) - bisect.bisect_right(ts, t_s)
    if len(ts) < MIN_SAMPLES or n_before < MIN_EACH_SIDE or n_after < MIN_EACH_SIDE:
        return None
    return fitted_delta(np.asarray(ts, dtype=np.float64) - t_s, np.asarray(q_slerp), qs)


def rotvec_matrix(d: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation of rotation vector `d`."""
    theta = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    kx = np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
    if theta < 1e-12:
        return np.eye(3) + kx
    return (np.eye(3) + math.sin(theta) / theta * kx
            + (1.0 - math.cos(theta)) / (theta * theta) * (kx @ kx))


def fitted_delta(tau_s: np.ndarray, q_slerp: np.ndarray, qs: np.ndarray) -> np.ndarray:
    """The quadratic fitted to the samples `qs` (N, 4, xyzw) at `tau_s`, its
    value at tau = 0 as a rotation from `q_slerp` (the slerped attitude
    there): 3x3, applied on the right. One window holding every sample."""
    d, _ = _ici()(np.ascontiguousarray(tau_s, dtype=np.float64),
                  np.ascontiguousarray(q_slerp, dtype=np.float64),
                  np.ascontiguousarray(qs, dtype=np.float64), _ALL, 0.0, ICI_GAMMA, 0.0)
    return rotvec_matrix(d)


def warm_up() -> None:
    """Compile (or load from numba's disk cache) before the first frame."""
    q = np.array([[0.0, 0.0, 0.0, 1.0]] * 5)
    fitted_delta(np.linspace(-0.02, 0.02, 5), q[0], q)
    adaptive_fit(0.0, [-0.02, -0.01, 0.0, 0.01, 0.02], q, q[0], 0.0, np.array([0.01, 0.02]), 1e-3)


def adaptive_fit(t_s: float, ts: list[float], qs: np.ndarray, q_slerp, w_slerp: float,
                 halves_s: np.ndarray, noise_sd_rad: float) -> np.ndarray | None:
    """`local_fit` over the widest of the half windows `halves_s` (increasing,
    `_ladder`) that the data allow, for an AHRS whose samples carry white
    noise of `noise_sd_rad` per axis (`ts`, `qs`: the samples within the
    widest; `w_slerp`: where t_s lies between its two neighbours, 0-1).

    A wider window averages more jitter but flattens more of the motion; the
    Intersection of Confidence Intervals rule (Goldenshluger & Nemirovski
    1997; Katkovnik 1999) picks it from the data: the estimates of windows
    +-half_s, x1.5, x1.5^2, ... are taken in turn, each with its interval
    +-ICI_GAMMA x its sd (noise x the square root of the fit's leverage), and
    the widest whose interval still meets all narrower ones wins. While the
    windows agree within their noise their bias is below it; once the motion
    bends the wider fit away, the intervals part. The narrowest estimate is
    the fit over +-half_s, or the slerp where that is too sparse (an attitude
    sampled at the frame times). None: the slerp stands."""
    d, found = _ici()(np.asarray(ts, dtype=np.float64) - t_s, np.asarray(q_slerp, dtype=np.float64),
                      np.ascontiguousarray(qs, dtype=np.float64), halves_s, noise_sd_rad, ICI_GAMMA,
                      w_slerp)
    return rotvec_matrix(d) if found else None


def _ici_py(tau_s: np.ndarray, q0: np.ndarray, qs: np.ndarray, halves: np.ndarray,
            noise_sd_rad: float, gamma: float, w_slerp: float) -> tuple[np.ndarray, bool]:
    """adaptive_fit's windows in one pass (numba): the samples' rotation
    vectors log(q0^-1 q_i) (the shorter way) once, then per window the
    normal equations of the quadratic in tau, its value at 0 and, from its
    leverage e0^T (A^T A)^-1 e0, its interval. Returns the chosen value
    (a rotation vector from q0) and whether a fit was chosen (the slerp:
    zeros, False). About 2 us for 9 samples, against ~150 us in numpy."""
    n = len(tau_s)
    x0, y0, z0, w0 = -q0[0], -q0[1], -q0[2], q0[3]
    v = np.empty((n, 3))
    for i in range(n):
        x, y, z, w = qs[i, 0], qs[i, 1], qs[i, 2], qs[i, 3]
        rx = w0 * x + x0 * w + y0 * z - z0 * y
        ry = w0 * y - x0 * z + y0 * w + z0 * x
        rz = w0 * z + x0 * y - y0 * x + z0 * w
        rw = w0 * w - x0 * x - y0 * y - z0 * z
        if rw < 0.0:
            rx, ry, rz, rw = -rx, -ry, -rz, -rw
        sn = np.sqrt(rx * rx + ry * ry + rz * rz)
        k = 2.0 * np.arctan2(sn, rw) / sn if sn > 1e-12 else 2.0
        v[i, 0], v[i, 1], v[i, 2] = rx * k, ry * k, rz * k
    e0 = np.zeros(3)
    e0[0] = 1.0
    best = np.zeros(3)
    found = False
    lo = np.full(3, -np.inf)
    hi = np.full(3, np.inf)
    for j in range(len(halves)):
        ata = np.zeros((3, 3))
        atv = np.zeros((3, 3))
        count, before, after = 0, 0, 0
        for i in range(n):
            t = tau_s[i]
            if abs(t) > halves[j]:
                continue
            count += 1
            if t < 0.0:
                before += 1
            elif t > 0.0:
                after += 1
            basis = (1.0, t, t * t)
            for a in range(3):
                for b in range(3):
                    ata[a, b] += basis[a] * basis[b]
                    atv[a, b] += basis[a] * v[i, b]
        fit = count >= MIN_SAMPLES and before >= MIN_EACH_SIDE and after >= MIN_EACH_SIDE
        if fit:
            d = np.linalg.solve(ata, atv)[0]
            sd = noise_sd_rad * np.sqrt(max(np.linalg.solve(ata, e0)[0], 0.0))
        elif j == 0:  # the slerp between the two neighbours
            d = np.zeros(3)
            sd = noise_sd_rad * np.sqrt((1.0 - w_slerp) ** 2 + w_slerp ** 2)
        else:
            continue
        parted = False
        for a in range(3):
            lo[a] = max(lo[a], d[a] - gamma * sd)
            hi[a] = min(hi[a], d[a] + gamma * sd)
            parted = parted or lo[a] > hi[a]
        if parted:
            break
        best, found = d, fit
    return best, found


_ici_compiled = None


def _ici():
    """The kernel compiled on first use (numba's disk cache after the first
    process): importing the attitude buffer, e.g. to load a configuration,
    costs no numba import."""
    global _ici_compiled
    if _ici_compiled is None:
        from numba import njit
        _ici_compiled = njit(cache=True, nogil=True)(_ici_py)
    return _ici_compiled


def _ladder(half_s: float, max_half_s: float) -> list[float]:
    """adaptive_fit's half windows: half_s, x LADDER_STEP, ..., max_half_s."""
    halves = [half_s]
    while halves[-1] * LADDER_STEP < max_half_s - 1e-9:
        halves.append(halves[-1] * LADDER_STEP)
    if max_half_s > half_s:
        halves.append(max_half_s)
    return halves


class FixedWindow:
    """An attitude source's look-ups with the fit over +-smoothing_s alone,
    never widened (`without_widening`); everything else is the source's."""

    def __init__(self, source) -> None:
        self.source = source

    def rotation_at(self, t_s: float) -> np.ndarray | None:
        return self.source.rotation_at(t_s, widen=False)

    def __getattr__(self, name: str):
        return getattr(self.source, name)


def without_widening(source):
    """`source` as it looks up the attitude without the ICI widening, for a
    consumer whose model takes each frame's attitude error as white: a fit
    over +-100 ms leaves an error correlated over about six frames (the
    fused tracker, docs/fusion.md). A source that does not widen is
    returned as it is."""
    return FixedWindow(source) if getattr(source, "widens", False) else source
