"""Attitude for replay: a recorded or ground-truth orientation series, with a
realistic AHRS error model (white noise, bias random walk, time offset).

NI-SLAM was evaluated on TUM with the motion-capture orientation standing in
for the attitude sensor; `attitude_for_replay` does the same when a sequence
has no `attitude.txt`, and the error model makes it look like a real AHRS.
"""

from __future__ import annotations

import bisect
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from onboard import NislamError
from onboard.core.attitude_smoothing import DEFAULT_HALF_S, DEFAULT_MAX_HALF_S, Window
from onboard.core.rotations import quat_slerp, quat_to_matrix
from onboard.core.trajectory import Trajectory
from sim_replay.tum import Sequence

DEFAULT_MAX_GAP_S = 0.2  # same rule as ground truth: bridge gaps up to 200 ms, never extrapolate
_GAP_EPS_S = 1e-9  # the tolerance Trajectory.interpolate uses, so both paths agree


class AttitudeSeries:
    """`AttitudeSource` over timestamped orientations R_W_C (positions ignored).

    `rotation_at` is called once per frame in the loop, so it works on plain
    Python floats (bisect + one slerp, a few microseconds) instead of building
    scipy Rotation objects per call.
    """

    def __init__(self, trajectory: Trajectory, max_gap_s: float = DEFAULT_MAX_GAP_S,
                 smoothing_s: float = DEFAULT_HALF_S, smoothing_max_s: float = 0.0,
                 noise_sd_deg: float = 0.0) -> None:
        """`smoothing_s`, `smoothing_max_s`, `noise_sd_deg`: as
        onboard.core.attitude.AttitudeBuffer's."""
        self.trajectory = trajectory
        self.max_gap_s = float(max_gap_s)
        self.smoothing_s = float(smoothing_s)
        self._window = Window(smoothing_s, smoothing_max_s, noise_sd_deg)
        self._t_s: list[float] = [float(t) for t in trajectory.t_s]
        self._q_xyzw: list[tuple[float, float, float, float]] = [
            (float(q[0]), float(q[1]), float(q[2]), float(q[3])) for q in trajectory.q_xyzw
        ]
        self._q_arr = np.asarray(self._q_xyzw, dtype=np.float64).reshape(-1, 4)

    def __len__(self) -> int:
        return len(self._t_s)

    @property
    def span_s(self) -> tuple[float, float] | None:
        return (self._t_s[0], self._t_s[-1]) if self._t_s else None

    @property
    def widens(self) -> bool:
        """As onboard.core.attitude.AttitudeBuffer.widens."""
        return self._window.widens

    def rotation_at(self, t_s: float, widen: bool = True) -> np.ndarray | None:
        """R_W_C (3x3) at `t_s`, slerped between the two neighbouring samples
        or fitted to those around it (`smoothing_s`, as the live buffer does,
        `widen` as its);
        None outside the covered span or inside a gap longer than `max_gap_s`."""
        q = self._quat_at(t_s)
        if q is None:
            return None
        r = quat_to_matrix(q)
        if self.smoothing_s <= 0.0:
            return r
        w = self._window
        i0 = bisect.bisect_left(self._t_s, t_s - w.widest_s)
        i1 = bisect.bisect_right(self._t_s, t_s + w.widest_s)
        delta = w.fit(t_s, self._t_s[i0:i1], self._q_arr[i0:i1], q, widen)
        return r if delta is None else r @ delta

    def _quat_at(self, t_s: float) -> tuple[float, float, float, float] | None:
        ts = self._t_s
        if not ts or not (ts[0] <= t_s <= ts[-1]):  # also rejects NaN
            return None
        i = bisect.bisect_right(ts, t_s)  # 1 <= i <= n here
        if ts[i - 1] == t_s:
            # A sample is valid at its own stamp even when a long gap follows it.
            return self._q_xyzw[i - 1]
        t0, t1 = ts[i - 1], ts[i]
        if t1 - t0 > self.max_gap_s + _GAP_EPS_S:
            return None
        return quat_slerp(self._q_xyzw[i - 1], self._q_xyzw[i], (t_s - t0) / (t1 - t0))

    def rotations_at(self, t_s) -> tuple[np.ndarray, np.ndarray]:
        """The samples slerped at `t_s`, vectorised: `rotation_at` without the
        local fit. (R_W_C (M,3,3), valid (M,) bool); invalid rows are NaN."""
        q, valid = _interpolate_q(self.trajectory, t_s, self.max_gap_s)
        r = np.full((len(valid), 3, 3), np.nan)
        if valid.any():
            r[valid] = Rotation.from_quat(q[valid]).as_matrix()
        return r, valid


def _interpolate_q(traj: Trajectory, t_s, max_gap_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Trajectory.interpolate's orientation, plus exact hits on a sample stamp.

    Trajectory.interpolate judges a query by the gap to the NEXT sample, so a
    sample bordering a gap longer than max_gap_s is rejected even at its own
    stamp; here a sample always stands for itself.
    """
    t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
    _p, q, valid = traj.interpolate(t, max_gap_s)
    if len(traj) and not valid.all():
        k = np.clip(np.searchsorted(traj.t_s, t), 0, len(traj) - 1)
        exact = ~valid & (traj.t_s[k] == t)
        q[exact] = traj.q_xyzw[k[exact]]
        valid = valid | exact
    return q, valid


@dataclass(frozen=True)
class AttitudeErrorModel:
    """How a simulated AHRS deviates from the truth.

    noise_deg: per-axis std of a white rotation-vector error drawn per sample.
    bias_deg_per_sqrt_s: random-walk intensity of a rotation-vector bias (per
        axis, starting at zero at the first sample; its variance grows as
        bias^2 * elapsed time).
    offset_ms: the sample stamped t holds the true attitude at t - offset (the
        sensor's stamps are late by offset; negative = early).
    seed: numpy Generator seed; the same seed gives the same errors.
    Errors act in the body frame: R_meas = R_true * Exp(bias) * Exp(noise).
    """

    noise_deg: float = 0.0
    bias_deg_per_sqrt_s: float = 0.0
    offset_ms: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("noise_deg", "bias_deg_per_sqrt_s", "offset_ms"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise NislamError(
                    f"attitude error model: {name} must be a finite number, got {v!r}"
                )
        if self.noise_deg < 0 or self.bias_deg_per_sqrt_s < 0:
            raise NislamError(
                "attitude error model: noise_deg and bias_deg_per_sqrt_s must be >= 0"
            )

    @property
    def is_zero(self) -> bool:
        return self.noise_deg == 0 and self.bias_deg_per_sqrt_s == 0 and self.offset_ms == 0

    def describe(self) -> str:
        if self.is_zero:
            return "exact"
        return (f"noise {self.noise_deg:g} deg, bias {self.bias_deg_per_sqrt_s:g} deg/sqrt(s), "
                f"offset {self.offset_ms:g} ms, seed {self.seed}")


def apply_error_model(
    truth: Trajectory,
    t_s,
    model: AttitudeErrorModel,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
) -> Trajectory:
    """Measured orientation samples stamped `t_s` (sorted): the truth
    interpolated at t - offset (stamps without truth there are dropped), then
    bias random walk and white noise applied in the body frame."""
    t = np.asarray(t_s, dtype=np.float64).ravel()
    q_true, valid = _interpolate_q(truth, t - model.offset_ms * 1e-3, max_gap_s)
    t, q_true = t[valid], q_true[valid]
    q_meas = perturb_samples(t, q_true, model)
    return Trajectory.from_samples(t, np.zeros((len(t), 3)), q_meas)


def perturb_samples(t_s, q_true_xyzw, model: AttitudeErrorModel) -> np.ndarray:
    """Bias random walk and white noise of `model` applied in the body frame to
    true orientations already taken at the sensor's stamps minus its offset
    (`t_s` sorted, only the intervals matter). Returns q_meas_xyzw (N, 4)."""
    t = np.asarray(t_s, dtype=np.float64).ravel()
    q_true = np.asarray(q_true_xyzw, dtype=np.float64).reshape(-1, 4)
    n = len(t)
    if n == 0 or (model.noise_deg == 0 and model.bias_deg_per_sqrt_s == 0):
        return q_true.copy()
    rng = np.random.default_rng(model.seed)
    # Draw both streams always, so switching one term on or off does not change
    # the realisation of the other for the same seed.
    noise_rad = rng.standard_normal((n, 3)) * math.radians(model.noise_deg)
    steps = rng.standard_normal((n, 3))
    dt_s = np.diff(t, prepend=t[0])
    bias_rad = np.cumsum(steps * (math.radians(model.bias_deg_per_sqrt_s) * np.sqrt(dt_s))[:, None],
                         axis=0)
    r_true = Rotation.from_quat(q_true)
    r_meas = r_true * Rotation.from_rotvec(bias_rad) * Rotation.from_rotvec(noise_rad)
    return r_meas.as_quat()


def attitude_for_replay(
    seq: Sequence, model: AttitudeErrorModel, max_gap_s: float = DEFAULT_MAX_GAP_S,
    smoothing_s: float = DEFAULT_HALF_S, smoothing_max_s: float = DEFAULT_MAX_HALF_S,
    ahrs_noise_deg: float = 0.0,
) -> tuple[AttitudeSeries, str]:
    """The attitude a replay feeds the tracker, and a label saying where it came from.

    From `attitude.txt` (R_W_B at the AHRS's own stamps, turned into R_W_C with
    the camera mount) when present; else from ground truth (the camera's own
    orientation, mount = identity, as the NI-SLAM authors did on TUM) at its
    own stamps: the motion capture is the attitude sensor, and it is played at
    its own rate as the service's replay plays it (sources.open_replay) and as
    a live AHRS arrives, so the same local fit takes out its white noise
    (docs/nislam-error-budget.md, "The motion capture's own rate"). The error
    model is applied in the body frame, per sample.
    Its white noise (`recorded_noise_deg`, with `ahrs_noise_deg` for a real
    AHRS's recording) and what the model adds, in quadrature: the local fit
    widens its window up to `smoothing_max_s` against it
    (onboard.core.attitude_smoothing.adaptive_fit).
    """
    if seq.attitude is not None:
        measured = apply_error_model(seq.attitude, seq.attitude.t_s, model, max_gap_s)
        q_b_c = np.asarray(seq.camera.q_B_C_xyzw, dtype=np.float64)
        if not np.allclose(q_b_c, [0.0, 0.0, 0.0, 1.0]):
            q_w_c = (Rotation.from_quat(measured.q_xyzw) * Rotation.from_quat(q_b_c)).as_quat()
            measured = Trajectory(measured.t_s, measured.p_xyz_m, q_w_c)
        source = "attitude.txt"
    elif seq.groundtruth is not None:
        measured = apply_error_model(seq.groundtruth, seq.groundtruth.t_s, model, max_gap_s)
        source = "groundtruth.txt (camera orientation, mount identity)"
    else:
        raise NislamError(
            f"{seq.path} has neither attitude.txt nor groundtruth.txt: no attitude to replay"
        )
    if len(measured) == 0:
        raise NislamError(f"{seq.path}: {source} gives no attitude sample at any frame time")
    noise_deg = math.hypot(recorded_noise_deg(seq, ahrs_noise_deg), model.noise_deg)
    return (AttitudeSeries(measured, max_gap_s, smoothing_s, smoothing_max_s, noise_deg),
            f"{source}; {model.describe()}")


def stated_noise_deg(seq_dir: Path | str) -> float | None:
    """The white attitude noise [deg per axis] a simulated flight's AHRS was
    given (its sim.json, `nislam sim --ahrs-profile`); None for a recording
    that does not state it (a real one). The replay tells NI-SLAM this
    instead of the configured default (`[nislam] attitude_sd_deg`, a
    myAHRS+'s 0.1 deg), so its covariance says what the flight's AHRS does:
    with an exact attitude the default over-states NI-SLAM's error ~5x and
    the fusion leans on FastORB for nothing (docs/fusion.md, "Coverage")."""
    path = Path(seq_dir) / "sim.json"
    try:
        errors = json.loads(path.read_text())["options"]["ahrs"]["errors"]
        noise = float(errors["noise_deg"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return noise if math.isfinite(noise) and noise >= 0.0 else None


def recorded_noise_deg(seq: Sequence, ahrs_noise_deg: float) -> float:
    """The white noise per axis [deg] of the attitude a replay of `seq` plays:
    what a simulated flight states (sim.json); for a real AHRS's recording
    (attitude.txt) the configured figure, `ahrs_noise_deg` (`[nislam]
    attitude_sd_deg`, what the live buffer takes); ground truth: none."""
    stated = stated_noise_deg(seq.path)
    if stated is not None:
        return stated
    return ahrs_noise_deg if seq.attitude is not None else 0.0
