"""The AHRS-to-camera time-offset calibration (onboard/nislam/calibration.py:
body_rate, OffsetCalibration, used as the NI-SLAM tracker uses them) with a
realistic AHRS: the simulator's profiles (white noise plus bias random walk,
sim_replay.sensors.AHRS_PROFILES, applied by the replay's own error model),
offsets of -30, 0 and +30 ms. The residual the images would show is taken
exact from the truth (its measurement is tests/test_rotation_residual.py);
scripts/offset_calibration.py runs the whole tracker on rendered flights."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from onboard.core.rotations import so3_log
from onboard.core.trajectory import Trajectory
from onboard.nislam.calibration import OffsetCalibration, body_rate
from onboard.nislam.params import NislamParams
from sim_replay.attitude import AttitudeErrorModel, AttitudeSeries, apply_error_model
from sim_replay.sensors import AHRS_PROFILES

P = NislamParams()
SECONDS, CAMERA_HZ, AHRS_HZ, KEY_S = 20.0, 30.0, 100.0, 0.5


def truth() -> Trajectory:
    """Camera orientation swinging like the `aggressive` flight: yaw up to
    ~90 deg/s, pitch and roll a few tens of deg/s, at unrelated frequencies."""
    t = np.arange(-1.0, SECONDS + 1.0, 1e-3)
    rotvec = np.stack([0.25 * np.sin(2 * np.pi * 0.45 * t + 1.0),
                       0.20 * np.sin(2 * np.pi * 0.7 * t),
                       0.35 * np.sin(2 * np.pi * 0.4 * t) + 0.3 * t], axis=1)
    q = Rotation.from_euler("zyx", rotvec[:, ::-1]).as_quat()
    return Trajectory.from_samples(t, np.zeros((len(t), 3)), q)


def calibrate(true: Trajectory, model: AttitudeErrorModel) -> float:
    """The tracker's calibration loop: each frame's residual rotation against
    its key (exact), the rate difference from the AHRS, one update."""
    ahrs = AttitudeSeries(apply_error_model(true, np.arange(0.0, SECONDS, 1 / AHRS_HZ), model))
    exact = AttitudeSeries(true)
    calib = OffsetCalibration(P.time_offset_forget, P.time_offset_max_s, 0.0)
    t_key = 0.1
    for t in np.arange(0.1, SECONDS - 0.1, 1 / CAMERA_HZ):
        if t - t_key >= KEY_S:
            t_key = t
        o = calib.offset_s
        r_key, r_cur = ahrs.rotation_at(t_key + o), ahrs.rotation_at(t + o)
        r_rel = r_key.T @ r_cur  # what the tracker projects the frame with
        true_rel = exact.rotation_at(t_key).T @ exact.rotation_at(t)
        # The residual the images show, in key axes, in the estimator's sign
        # (an error e in the current axes shows as -R_rel e).
        theta = -r_rel @ so3_log(true_rel.T @ r_rel)
        w_cur = body_rate(ahrs, t + o, P.rate_half_window_s)
        w_key = body_rate(ahrs, t_key + o, P.rate_half_window_s)
        calib.update((w_key - r_rel @ w_cur)[:2], theta[:2])
    return calib.offset_s


@pytest.mark.parametrize("profile", ["myahrs", "autopilot"])
def test_offset_recovered_within_3ms_with_a_realistic_ahrs(profile: str) -> None:
    prof = AHRS_PROFILES[profile]
    true = truth()
    for offset_ms in (-30.0, 0.0, 30.0):
        for seed in (0, 1):
            model = AttitudeErrorModel(prof["noise_deg"], prof["bias_deg_per_sqrt_s"],
                                       offset_ms, seed)
            est_ms = calibrate(true, model) * 1e3
            assert abs(est_ms - offset_ms) < 3.0, (profile, offset_ms, seed, est_ms)

