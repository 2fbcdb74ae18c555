"""FastORB's per-frame pose on what real cameras add (issue 18,
docs/fastorb_backend.md "Real data"): a PnP re-fit that lands far off, and a
rolling shutter under a fast turn."""

from __future__ import annotations

import numpy as np

from onboard.core.se3 import inverse, se3_exp
from onboard.fastorb import pose as fastorb_pose
from onboard.fastorb.motion import project
from onboard.fastorb.pose import PnpSettings, solve_pnp
from onboard.fastorb.shutter import pixels_at_mid, points_at_mid, twist_rate

K = np.array([[517.3, 0.0, 318.6], [0.0, 516.5, 255.3], [0.0, 0.0, 1.0]])
W, H = 640, 480


def _scene(n: int = 400, seed: int = 3) -> np.ndarray:
    """World points 1-3 m in front of a camera at the origin looking along +z."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(1.0, 3.0, n)
    u, v = rng.uniform(20, W - 20, n), rng.uniform(20, H - 20, n)
    return np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)


def _truth() -> np.ndarray:
    return se3_exp(np.array([0.02, -0.03, 0.01, 0.05, -0.02, 0.03]))


def test_a_ransac_refit_far_off_is_replaced_by_the_motion_prior(monkeypatch):
    """OpenCV re-fits an AP3P consensus set with EPnP; on `circle` that re-fit
    came back 1.3 m off (12.7 px median error) and the refinement stayed
    there, so the track was lost. With the motion model's prediction the
    refinement starts from whichever pose more points agree with."""
    X = _scene()
    T = _truth()
    uv = project(K, T, X)[0] + np.random.default_rng(1).normal(0, 0.3, (len(X), 2))
    far = se3_exp(np.array([0.0, 2.0, 0.0, 0.9, -0.6, 0.7])) @ T  # turned 115 deg: no way back
    all_in = np.ones(len(X), bool)
    monkeypatch.setattr(fastorb_pose, "_ransac", lambda *a: (far, all_in))
    s = PnpSettings()
    prior = se3_exp(np.array([0.004, 0.0, -0.003, 0.01, 0.005, 0.0])) @ T  # a frame's misprediction
    fit = solve_pnp(X, uv, K, s, 30, prior=prior)
    assert fit is not None and fit.inliers.sum() > 0.95 * len(X)
    err = inverse(fit.T_cw) @ T
    assert np.linalg.norm(err[:3, 3]) < 2e-3
    # Without the prior the far re-fit is all there is: no pose (or a wrong one).
    bad = solve_pnp(X, uv, K, s, 30)
    assert bad is None or np.linalg.norm((inverse(bad.T_cw) @ T)[:3, 3]) > 0.05
    # A RANSAC pose that more points agree with than with the prior wins.
    monkeypatch.setattr(fastorb_pose, "_ransac", lambda *a: (T, all_in))
    fit = solve_pnp(X, uv, K, s, 30, prior=far)
    assert fit is not None and np.linalg.norm((inverse(fit.T_cw) @ T)[:3, 3]) < 2e-3


def _rolling_shutter_pixels(X, T_mid, xi, readout):
    """Pixels of a rolling-shutter camera: each point is seen in the row whose
    instant's pose projects it there (fixed-point iteration on the row)."""
    uv = project(K, T_mid, X)[0]
    for _ in range(10):
        tau = readout * (uv[:, 1] / H - 0.5)
        out = np.empty_like(uv)
        for i in range(len(X)):
            out[i] = project(K, se3_exp(tau[i] * xi) @ T_mid, X[i:i + 1])[0][0]
        uv = out
    return uv


def test_rolling_shutter_pixels_and_points_come_back_to_the_middle_row():
    X = _scene(120)
    T_mid = _truth()
    xi = np.array([0.4, 1.1, -0.3, 0.2, -0.1, 0.05])  # 68 deg/s, 0.23 m/s (tum_fr1_rpy's pace)
    readout = 0.028
    uv_rs = _rolling_shutter_pixels(X, T_mid, xi, readout)
    uv_mid, z_mid = project(K, T_mid, X)
    shear = np.linalg.norm(uv_rs - uv_mid, axis=1)
    assert shear.max() > 4.0  # what a global-shutter model would have to swallow
    back = pixels_at_mid(uv_rs, z_mid, K, xi, readout, H)
    assert np.abs(back - uv_mid).max() < 0.15
    # Landmarks from a pixel and its (row-time) depth land where they are.
    p_row = np.array([(se3_exp(t * xi) @ T_mid @ np.append(x, 1.0))[:3]
                      for t, x in zip(readout * (uv_rs[:, 1] / H - 0.5), X)])
    p = points_at_mid(uv_rs, p_row[:, 2], K, xi, readout, H)
    X_back = (p - T_mid[:3, 3]) @ T_mid[:3, :3]
    assert np.abs(X_back - X).max() < 1e-3
    # No readout or no motion: nothing moves.
    assert np.array_equal(pixels_at_mid(uv_rs, z_mid, K, xi, 0.0, H), uv_rs)
    assert np.array_equal(pixels_at_mid(uv_rs, z_mid, K, np.zeros(6), readout, H), uv_rs)
    # The twist a motion model hands over is per second.
    T1 = se3_exp(0.033 * xi) @ T_mid
    assert np.allclose(twist_rate(T_mid, T1, 0.033), xi, atol=1e-9)


def test_a_rolling_shutter_pose_is_found_with_the_correction_and_biased_without():
    X = _scene(300, seed=5)
    T_mid = _truth()
    xi = np.array([0.3, 1.2, -0.2, 0.1, 0.0, 0.0])
    readout = 0.028
    uv_rs = _rolling_shutter_pixels(X, T_mid, xi, readout)
    s = PnpSettings(bf_px=0.0)
    plain = solve_pnp(X, uv_rs, K, s, 30, prior=T_mid)
    fixed = solve_pnp(X, pixels_at_mid(uv_rs, project(K, T_mid, X)[1], K, xi, readout, H), K,
                      s, 30, prior=T_mid)

    def angle_deg(T):
        d = T @ inverse(T_mid)
        return np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1)))

    assert fixed is not None and fixed.inliers.all()
    assert angle_deg(fixed.T_cw) < 0.01
    assert plain is None or plain.inliers.sum() < len(X) or angle_deg(plain.T_cw) > 0.05


def test_the_rows_shear_measures_the_rate_the_motion_model_got_wrong():
    """The rate from two poses is half a frame old and as noisy as they are;
    the shear of a few hundred points over the rows measures it."""
    from onboard.fastorb.shutter import refine_with_rate

    X = _scene(300, seed=7)
    T_mid = _truth()
    xi = np.array([0.5, 1.3, -0.4, 0.1, 0.05, 0.0])
    readout = 0.028
    uv_rs = _rolling_shutter_pixels(X, T_mid, xi, readout)
    guess = xi.copy()
    guess[:3] += np.array([0.4, -0.5, 0.3])  # 40 deg/s off
    start = se3_exp(np.array([0.003, -0.002, 0.001, 0.004, 0.002, -0.003])) @ T_mid
    T, omega = refine_with_rate(start, X, uv_rs, np.zeros(len(X)), K, 0.0, 1.0, readout, H,
                                guess, rate_sd=0.5)
    assert np.linalg.norm(omega - xi[:3]) < 0.05
    assert np.linalg.norm((T @ inverse(T_mid))[:3, 3]) < 1e-3
    # A global shutter (no readout) leaves nothing to measure: the prior stays.
    T0, omega0 = refine_with_rate(start, X, project(K, T_mid, X)[0], np.zeros(len(X)), K, 0.0,
                                  1.0, 0.0, H, guess, rate_sd=0.5)
    assert np.allclose(omega0, guess[:3], atol=1e-6)


def test_the_readout_is_the_cameras_unless_configured(tmp_path):
    """A rolling shutter is a property of the camera: the TUM reader knows
    the Kinect-class cameras', a camera.toml may give one, the synthetic
    flights' (no key) is a global shutter; [fastorb] overrides it."""
    import pytest

    from onboard import NislamError
    from onboard.core.camera import CameraIntrinsics
    from onboard.fastorb.params import FastOrbParams
    from onboard.fastorb.tracker import FastOrbTracker
    from sim_replay.tum_files import load_camera

    fr1 = tmp_path / "rgbd_dataset_freiburg1_rpy"
    fr1.mkdir()
    assert load_camera(fr1).intrinsics().readout_s == 0.028
    own = tmp_path / "own"
    own.mkdir()
    base = "fx = 500.0\nfy = 500.0\ncx = 320.0\ncy = 240.0\nwidth = 640\nheight = 480\n"
    (own / "camera.toml").write_text(base + "depth_scale = 1000.0\n")
    assert load_camera(own).readout_s == 0.0
    (own / "camera.toml").write_text(base + "depth_scale = 1000.0\nreadout_s = 0.02\n")
    assert load_camera(own).readout_s == 0.02
    (own / "camera.toml").write_text(base + "depth_scale = 1000.0\nreadout_s = 0.5\n")
    with pytest.raises(NislamError, match="readout_s"):
        load_camera(own)
    intr = CameraIntrinsics(500.0, 500.0, 320.0, 240.0, 640, 480, 0.028)
    assert FastOrbTracker(intr).p.rolling_shutter_readout_s == 0.028
    off = FastOrbParams(rolling_shutter_readout_s=0.0)
    assert FastOrbTracker(intr, off).p.rolling_shutter_readout_s == 0.0
