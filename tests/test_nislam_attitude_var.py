"""NI-SLAM's reported covariance carries the attitude's own error: the AHRS's
white noise moves the correlation peak by depth x error on the key's two
lateral axes, not along its optical axis (onboard/nislam/attitude_var.py)."""

from __future__ import annotations

import dataclasses
import math
import types

import numpy as np
from test_nislam import INTR, Scene, _params, _track_poses

from onboard.core.messages import TrackResult
from onboard.fusion.measurements import key_attitude_cov, nislam_cov
from onboard.fusion.params import FusionParams
from onboard.fusion.registry import _make_nislam
from onboard.nislam.attitude_var import attitude_lateral_var_m2, with_attitude_var
from onboard.nislam.tracker import NislamTracker

# Camera looking along world +x (optical axis = world x): the key's lateral
# axes are world y and z.
R_ALONG_X = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def test_lateral_variance_grows_with_depth_and_attitude_sd():
    v = attitude_lateral_var_m2(2.0, 0.1)
    # key's and frame's attitude, each moving the peak by depth x sd
    assert math.isclose(v, 2.0 * (2.0 * math.radians(0.1)) ** 2)
    assert math.isclose(attitude_lateral_var_m2(4.0, 0.1), 4.0 * v)
    assert math.isclose(attitude_lateral_var_m2(2.0, 0.2), 4.0 * v)
    assert attitude_lateral_var_m2(2.0, 0.0) == 0.0
    assert attitude_lateral_var_m2(float("nan"), 0.1) == 0.0


def test_the_optical_axis_gets_none_of_it():
    base = np.array([1e-6, 2e-6, 3e-6, 1e-5, 1e-5, 1e-5])
    out = with_attitude_var(base, R_ALONG_X, 4e-4)
    np.testing.assert_allclose(out - base, [0.0, 4e-4, 4e-4, 0.0, 0.0, 0.0], atol=1e-15)
    # the fused filter: the frame's half white in the measurement, the key's
    # half on the key's clone; both in the key's lateral axes only
    r = TrackResult(
        t_s=0.0, state=None, trusted=True, p_W_m=np.zeros(3), R_W_C=R_ALONG_X, pose_var=base,
        quality=50, psr=80.0, keyframe_id=0, new_keyframe=False, reset_counter=0, lost_reason=None,
        shift_cells=(0.0, 0.0), tz_m=0.0, res_m=0.01, rotation_residual_rad=np.zeros(3),
        attitude_offset_s=0.0, matched_cells=5000,
    )
    p = FusionParams()
    grown = np.diag(nislam_cov(dataclasses.replace(r, attitude_var_m2=4e-4), p)) - np.diag(nislam_cov(r, p))
    np.testing.assert_allclose(grown, [0.0, 2e-4, 2e-4], rtol=1e-9, atol=1e-15)
    key = key_attitude_cov(dataclasses.replace(r, attitude_var_m2=4e-4))
    np.testing.assert_allclose(np.diag(key), [0.0, 2e-4, 2e-4], atol=1e-15)


def test_tracker_reports_it_without_moving_its_poses():
    """A wall at 3 m with a board at 1.8 m: the reported lateral variance grows
    by 2 (mean depth x sd)^2, the axial and the poses do not change."""
    poses = [(np.eye(3), np.array([0.01, -0.005, 0.01]) * k) for k in range(4)]
    exact = _track_poses(NislamTracker(INTR, _params(attitude_sd_deg=0.0)), Scene(21), poses)
    noisy = _track_poses(NislamTracker(INTR, _params(attitude_sd_deg=0.3)), Scene(21), poses)
    lo, hi = (attitude_lateral_var_m2(z, 0.3) for z in (1.8, 3.0))
    for a, b in zip(exact[1:], noisy[1:]):
        assert a.trusted and b.trusted
        np.testing.assert_array_equal(a.p_W_m, b.p_W_m)
        assert a.attitude_var_m2 == 0.0 and lo < b.attitude_var_m2 < hi
        # identity attitude: the key's axes are the world's, z the optical axis
        np.testing.assert_allclose(b.pose_var[:2] - a.pose_var[:2], b.attitude_var_m2, rtol=1e-9)
        assert b.pose_var[2] == a.pose_var[2]


def test_noise_a_replay_adds_comes_in_quadrature():
    cfg = types.SimpleNamespace(nislam=_params(attitude_sd_deg=0.1),
                                attitude=types.SimpleNamespace(noise_deg=1.0))
    assert math.isclose(_make_nislam(INTR, cfg).p.attitude_sd_deg, math.hypot(0.1, 1.0))
    cfg.attitude.noise_deg = 0.0
    assert _make_nislam(INTR, cfg).p.attitude_sd_deg == 0.1


def test_a_simulated_flight_tells_nislam_its_ahrs_noise(tmp_path) -> None:
    import json

    from onboard.app.config import load_config
    from onboard.app.replay import with_stated_ahrs

    cfg = load_config(None, {})
    assert with_stated_ahrs(cfg, tmp_path) is cfg  # a real recording: the configured AHRS
    (tmp_path / "sim.json").write_text(json.dumps({"options": {"ahrs": {"errors": {"noise_deg": 0.0}}}}))
    assert with_stated_ahrs(cfg, tmp_path).nislam.attitude_sd_deg == 0.0  # an exact attitude
    assert with_stated_ahrs(cfg, tmp_path).fusion == cfg.fusion
