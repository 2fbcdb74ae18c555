"""Sensor models of the synthetic flights: depth noise and holes, mounts, the
AHRS error model and its profiles."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from onboard import NislamError
from onboard.core.rotations import mount_rotation
from sim_replay.attitude import AttitudeErrorModel
from sim_replay.sensors import (
    AhrsModel,
    ColourNoise,
    DepthSensorModel,
    ahrs_profile,
    ahrs_sample_times,
    depth_to_png_units,
    measure_attitude,
    measure_depth,
)


def test_depth_noise_grows_with_the_square_of_depth():
    model = DepthSensorModel(sigma_m_per_m2=0.002, edge_rel=math.inf, edge_width_px=0)
    rng = np.random.default_rng(0)
    for z in (0.5, 1.0, 2.0, 4.0):
        truth = np.full((200, 300), z, np.float32)
        err = measure_depth(truth, model, rng).astype(np.float64) - z
        assert abs(err.mean()) < 0.05 * 0.002 * z * z
        assert abs(err.std() / (0.002 * z * z) - 1.0) < 0.02, (z, err.std())


def test_depth_is_invalid_out_of_range_and_at_depth_edges():
    model = DepthSensorModel(sigma_m_per_m2=0.0, min_range_m=0.3, max_range_m=5.0,
                             edge_rel=0.04, edge_width_px=1)
    rng = np.random.default_rng(0)
    near_far = measure_depth(np.array([[0.29, 0.31, 4.99, 5.01]] * 3, np.float32),
                             DepthSensorModel(0.0, 0.3, 5.0, edge_rel=math.inf), rng)
    assert (near_far[:, [0, 3]] == 0).all() and (near_far[:, [1, 2]] > 0).all()
    truth = np.full((20, 40), 2.0, np.float32)
    truth[:, 20:] = 3.0  # a step: the left surface stands in front of the right one
    out = measure_depth(truth, model, rng)
    # Columns 19 and 20 straddle the edge; one more pixel either side goes too.
    assert (out[:, 18:22] == 0).all()
    assert np.array_equal(out[:, :18], truth[:, :18]) and np.array_equal(out[:, 22:],
                                                                         truth[:, 22:])
    # A slanted floor seen far away is no edge.
    v = np.arange(100, dtype=np.float32)[:, None]
    floor = np.broadcast_to(1.0 / (0.25 + 0.002 * v), (100, 10)).astype(np.float32)
    assert (measure_depth(floor, model, np.random.default_rng(0))[1:-1] > 0).all()


def test_depth_dropout_share_and_png_units():
    model = DepthSensorModel(sigma_m_per_m2=0.0, edge_rel=math.inf, dropout=0.1)
    out = measure_depth(np.full((300, 300), 1.0, np.float32), model, np.random.default_rng(1))
    assert abs((out == 0).mean() - 0.1) < 0.01
    units = depth_to_png_units(np.array([[0.0, 1.23456, 20.0]], np.float32), 5000.0)
    assert units.dtype == np.uint16 and units.tolist() == [[0, 6173, 0]]


def test_colour_noise_std_and_determinism():
    noise = ColourNoise((60, 80), 3.0, seed=2)
    img = np.full((60, 80, 3), 128, np.uint8)
    a = noise.apply(img, np.random.default_rng(5)).astype(np.float64)
    b = noise.apply(img, np.random.default_rng(5))
    assert np.array_equal(a, b) and abs((a - 128).std() - 3.0) < 0.2
    assert noise.apply(img, np.random.default_rng(6)).astype(np.float64).tolist() != a.tolist()


def test_mount_presets_follow_the_design_conventions():
    fwd = mount_rotation("forward")  # columns: camera x, y, z in the body (FRD)
    assert fwd[:, 2].tolist() == [1, 0, 0] and fwd[:, 0].tolist() == [0, 1, 0]
    assert fwd[:, 1].tolist() == [0, 0, 1]
    assert np.allclose(Rotation.from_matrix(fwd).as_quat(), [0.5, 0.5, 0.5, 0.5])
    down = mount_rotation("down")
    assert down[:, 2].tolist() == [0, 0, 1] and np.isclose(np.linalg.det(down), 1.0)
    with pytest.raises(NislamError, match="unknown camera mount"):
        mount_rotation("sideways")


def _tumbling_R(t_s: np.ndarray) -> np.ndarray:
    rv = np.stack([0.5 * np.sin(0.6 * t_s), 0.3 * np.cos(0.4 * t_s), 0.2 * t_s], axis=1)
    return Rotation.from_rotvec(rv).as_matrix()


def _errors_deg(t, q_meas, offset_s=0.0):
    r_true = Rotation.from_matrix(_tumbling_R(t - offset_s))
    return np.degrees((r_true.inv() * Rotation.from_quat(q_meas)).as_rotvec())


def test_ahrs_error_statistics_match_the_configured_model():
    t = ahrs_sample_times(10.0, 1010.0, 100.0, phase_s=0.0037)
    assert np.allclose(np.diff(t), 0.01, atol=2e-6) and t[0] < 10.0 - 0.1 and t[-1] > 1010.1
    # White noise alone: per-axis std as configured.
    model = AhrsModel(100.0, AttitudeErrorModel(noise_deg=0.5, seed=3))
    ts, q = measure_attitude(t, _tumbling_R, model, np.random.default_rng(0))
    err = _errors_deg(ts, q)
    assert np.all(np.abs(err.std(axis=0) / 0.5 - 1.0) < 0.02), err.std(axis=0)
    assert np.all(np.abs(err.mean(axis=0)) < 0.01)
    # Bias random walk alone: increments over 1 s have std bias * sqrt(1 s).
    model = AhrsModel(100.0, AttitudeErrorModel(bias_deg_per_sqrt_s=0.2, seed=4))
    ts, q = measure_attitude(t, _tumbling_R, model, np.random.default_rng(0))
    walk = _errors_deg(ts, q)
    steps = walk[100::100] - walk[:-100:100]
    assert np.all(np.abs(steps.std(axis=0) / 0.2 - 1.0) < 0.1), steps.std(axis=0)
    # Offset alone: the sample stamped t holds the truth at t - offset, exactly.
    model = AhrsModel(100.0, AttitudeErrorModel(offset_ms=12.0))
    ts, q = measure_attitude(t[:500], _tumbling_R, model, np.random.default_rng(0))
    assert np.abs(_errors_deg(ts, q, offset_s=0.012)).max() < 1e-9
    assert np.abs(_errors_deg(ts, q)).max() > 0.01  # ... and not the truth at t
    # Dropout: that share of samples is missing, the others untouched.
    model = AhrsModel(100.0, AttitudeErrorModel(), dropout=0.05)
    ts, q = measure_attitude(t, _tumbling_R, model, np.random.default_rng(9))
    assert abs(1.0 - len(ts) / len(t) - 0.05) < 0.005
    assert np.abs(_errors_deg(ts, q)).max() < 1e-9


def test_ahrs_profiles():
    p = ahrs_profile("myahrs")
    assert set(p) == {"noise_deg", "bias_deg_per_sqrt_s", "offset_ms", "dropout"}
    assert p["noise_deg"] > 0 and ahrs_profile("perfect")["noise_deg"] == 0
    with pytest.raises(NislamError, match="unknown AHRS profile 'xsens'"):
        ahrs_profile("xsens")
    with pytest.raises(NislamError, match="dropout"):
        AhrsModel(100.0, AttitudeErrorModel(), dropout=1.0)
