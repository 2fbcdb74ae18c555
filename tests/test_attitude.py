"""Replay attitude: series lookup, ground-truth/attitude.txt sources, error model."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from onboard import NislamError
from onboard.core.trajectory import Trajectory
from sim_replay.attitude import (
    AttitudeErrorModel,
    AttitudeSeries,
    apply_error_model,
    attitude_for_replay,
)
from sim_replay.tum import open_sequence

SMALL_CAMERA_TOML = (
    "fx = 10.0\nfy = 10.0\ncx = 4.0\ncy = 3.0\nwidth = 8\nheight = 6\ndepth_scale = 1000.0\n"
)


def _small_sequence(
    seq_dir: Path, attitude_t_s=None, attitude_q_xyzw=None, camera_extra: str = ""
) -> Path:
    """One tiny RGB-D frame at t = 1.0 plus an optional attitude.txt."""
    (seq_dir / "rgb").mkdir(parents=True)
    (seq_dir / "depth").mkdir()
    cv2.imwrite(str(seq_dir / "rgb" / "1.png"), np.zeros((6, 8, 3), np.uint8))
    cv2.imwrite(str(seq_dir / "depth" / "1.png"), np.zeros((6, 8), np.uint16))
    (seq_dir / "rgb.txt").write_text("1.0 rgb/1.png\n")
    (seq_dir / "depth.txt").write_text("1.0 depth/1.png\n")
    (seq_dir / "camera.toml").write_text(SMALL_CAMERA_TOML + camera_extra)
    if attitude_t_s is not None:
        lines = ["# timestamp qx qy qz qw"]
        lines += [f"{t:.6f} {q[0]:.12f} {q[1]:.12f} {q[2]:.12f} {q[3]:.12f}"
                  for t, q in zip(attitude_t_s, attitude_q_xyzw)]
        (seq_dir / "attitude.txt").write_text("\n".join(lines) + "\n")
    return seq_dir


def _tumbling_q_xyzw(t_s: np.ndarray) -> np.ndarray:
    """A smooth, non-trivial orientation history (tens of deg/s about all axes)."""
    rotvec = np.stack([0.6 * np.sin(0.7 * t_s), 0.4 * np.cos(0.5 * t_s), 0.3 * t_s], axis=1)
    return Rotation.from_rotvec(rotvec).as_quat()


def _angle_deg(r_a: np.ndarray, r_b: np.ndarray) -> np.ndarray:
    return np.degrees(np.linalg.norm(
        (Rotation.from_matrix(r_a).inv() * Rotation.from_matrix(r_b)).as_rotvec(), axis=-1))


@pytest.fixture(scope="module")
def rpy(shared_data):
    return open_sequence(shared_data / "tum_fr1_rpy")


# --------------------------------------------------------------------------- ground-truth source


def test_zero_model_plays_every_groundtruth_sample(rpy):
    """The motion capture is the attitude sensor, played at its own 100 Hz (as
    the service's replay plays it), not resampled at the 30 Hz frame times:
    the local fit then has the samples it takes the sensor's white noise out with."""
    series, label = attitude_for_replay(rpy, AttitudeErrorModel(), smoothing_s=0.0)
    assert label.startswith("groundtruth.txt") and "exact" in label
    assert len(series) == len(rpy.groundtruth.t_s) == 2742
    gt = rpy.groundtruth
    np.testing.assert_allclose(np.stack([series.rotation_at(t) for t in gt.t_s[::50]]),
                               Rotation.from_quat(gt.q_xyzw[::50]).as_matrix(), atol=1e-12)
    # Between its samples both slerp alike, at every frame time.
    _p, q, valid = rpy.groundtruth_at(rpy.frame_times_s)
    assert valid.all() and len(rpy.frame_times_s) == 722
    r_gt = Rotation.from_quat(q).as_matrix()
    r_series = np.stack([series.rotation_at(t) for t in rpy.frame_times_s])
    np.testing.assert_allclose(r_series, r_gt, atol=1e-12)
    r_vec, ok = series.rotations_at(rpy.frame_times_s)
    assert ok.all()
    np.testing.assert_allclose(r_vec, r_gt, atol=1e-12)


def test_default_fit_takes_noise_out_of_the_groundtruth(rpy):
    """The motion capture's orientation jitters by 0.03-0.08 deg per sample.
    Over its own 100 Hz stamps the default local fit takes a third of the
    sample-to-sample jitter out (second differences of the rotation: 0.26 ->
    0.17 deg RMS, part of which is the true angular acceleration), and stays
    within a tenth of a degree of the samples."""
    gt = rpy.groundtruth
    t, truth = gt.t_s[100:-100], Rotation.from_quat(gt.q_xyzw[100:-100])

    def jitter_deg(r: Rotation) -> float:
        steps = (r[:-1].inv() * r[1:]).as_rotvec()
        return float(np.degrees(np.sqrt(np.mean(np.sum(np.diff(steps, axis=0) ** 2, axis=1)))))

    for smoothing_s, most in ((0.0, 1.0 + 1e-9), (0.04, 0.75)):
        series, _ = attitude_for_replay(rpy, AttitudeErrorModel(), smoothing_s=smoothing_s)
        played = Rotation.from_matrix(np.stack([series.rotation_at(x) for x in t]))
        assert jitter_deg(played) <= most * jitter_deg(truth)
        assert np.sqrt(np.mean(_angle_deg(played.as_matrix(), truth.as_matrix()) ** 2)) < 0.1


def test_scalar_and_vector_lookup_agree_between_samples(rpy):
    series, _ = attitude_for_replay(rpy, AttitudeErrorModel(), smoothing_s=0.0)
    t_mid = 0.5 * (rpy.frame_times_s[:-1] + rpy.frame_times_s[1:]) + 0.003
    r_vec, ok = series.rotations_at(t_mid)
    assert ok.sum() >= len(t_mid) - 5
    for t, r, good in zip(t_mid, r_vec, ok):
        got = series.rotation_at(t)
        if good:
            np.testing.assert_allclose(got, r, atol=1e-12)
        else:
            assert got is None and np.isnan(r).all()


@pytest.mark.parametrize("offset_ms", [30.0, -20.0])
def test_offset_resamples_truth_earlier(rpy, offset_ms):
    series, label = attitude_for_replay(rpy, AttitudeErrorModel(offset_ms=offset_ms),
                                        smoothing_s=0.0)
    assert f"offset {offset_ms:g} ms" in label
    t = rpy.frame_times_s
    _p, q_shift, ok = rpy.groundtruth_at(t - offset_ms * 1e-3)
    assert ok.sum() > 600
    r_series = np.stack([series.rotation_at(x) for x in t[ok]])
    # The shifted samples fall on the truth's own where its stamps are 10 ms
    # apart (30 and 20 ms are whole samples), near it elsewhere.
    dev = _angle_deg(r_series, Rotation.from_quat(q_shift[ok]).as_matrix())
    assert np.median(dev) < 1e-6 and np.quantile(dev, 0.98) < 0.01
    # ... and it really differs from the truth at the stamp (fr1/rpy turns fast)
    _p, q_now, _ok = rpy.groundtruth_at(t[ok])
    lag_deg = _angle_deg(r_series, Rotation.from_quat(q_now).as_matrix())
    assert np.median(lag_deg) > 0.3


def test_rotation_outside_span_or_nan_is_none(rpy):
    series, _ = attitude_for_replay(rpy, AttitudeErrorModel())
    t0, t1 = series.span_s
    assert series.rotation_at(t0 - 1e-3) is None
    assert series.rotation_at(t1 + 1e-3) is None
    assert series.rotation_at(float("nan")) is None
    assert series.rotation_at(t0) is not None and series.rotation_at(t1) is not None
    r, ok = series.rotations_at([t0 - 1.0, t1 + 1.0])
    assert not ok.any() and np.isnan(r).all()


def test_no_attitude_source_raises(tmp_path):
    seq = open_sequence(_small_sequence(tmp_path / "seq"))
    with pytest.raises(NislamError, match="neither attitude.txt nor groundtruth.txt"):
        attitude_for_replay(seq, AttitudeErrorModel())


# --------------------------------------------------------------------------- attitude.txt source


def test_attitude_txt_gap_and_mount(tmp_path):
    t = np.concatenate([np.arange(0.0, 1.0, 0.01), np.arange(1.3, 2.0, 0.01)])  # 310 ms gap
    q_w_b = _tumbling_q_xyzw(t)
    forward = "q_B_C_xyzw = [0.5, 0.5, 0.5, 0.5]\n"
    seq_dir = _small_sequence(tmp_path / "seq", t, q_w_b, camera_extra=forward)
    seq = open_sequence(seq_dir)
    # the samples themselves (no local fit: tests/test_attitude_smoothing.py)
    series, label = attitude_for_replay(seq, AttitudeErrorModel(), smoothing_s=0.0)
    assert label.startswith("attitude.txt")
    assert series.rotation_at(1.15) is None  # inside the 310 ms gap
    assert series.rotation_at(0.985) is not None and series.rotation_at(1.305) is not None
    # the samples bordering the gap hold at their own stamps (Trajectory.interpolate
    # alone would reject 0.99: it judges a query by the gap that follows it)
    assert len(series) == len(t)
    assert series.rotation_at(0.99) is not None and series.rotation_at(1.3) is not None
    r, ok = series.rotations_at([0.99, 1.15, 1.3])
    assert ok.tolist() == [True, False, True]
    # forward mount: camera z = body x, camera x = body y, camera y = body z
    r_b_c = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    for k in (0, 57, 150):
        expected = Rotation.from_quat(q_w_b[k]).as_matrix() @ r_b_c
        np.testing.assert_allclose(series.rotation_at(t[k]), expected, atol=1e-9)


def test_noise_statistics_match_configured_std(tmp_path):
    t = np.arange(5000) * 0.01
    seq = open_sequence(_small_sequence(tmp_path / "seq", t, _tumbling_q_xyzw(t)))
    model = AttitudeErrorModel(noise_deg=0.5, seed=11)
    series, _ = attitude_for_replay(seq, model)
    r_meas, ok = series.rotations_at(seq.attitude.t_s)
    assert ok.all() and len(series) == 5000
    r_true = Rotation.from_quat(seq.attitude.q_xyzw)
    err_deg = np.degrees((r_true.inv() * Rotation.from_matrix(r_meas)).as_rotvec())
    std = err_deg.std(axis=0)
    assert np.all(np.abs(std / 0.5 - 1.0) < 0.05), std
    assert np.all(np.abs(err_deg.mean(axis=0)) < 0.03)
    # white: consecutive samples uncorrelated
    corr = np.corrcoef(err_deg[:-1, 0], err_deg[1:, 0])[0, 1]
    assert abs(corr) < 0.05


# --------------------------------------------------------------------------- error model


def _identity_truth(t_s: np.ndarray) -> Trajectory:
    n = len(t_s)
    return Trajectory(t_s, np.zeros((n, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)))


def test_bias_random_walk_variance_grows_linearly():
    bias = 0.5  # deg/sqrt(s)
    t = np.arange(0.0, 10.0 + 1e-9, 0.05)
    truth = _identity_truth(t)
    k_quarter, k_end = int(round(2.5 / 0.05)), len(t) - 1
    b_quarter, b_end = [], []
    for seed in range(300):
        meas = apply_error_model(truth, t, AttitudeErrorModel(bias_deg_per_sqrt_s=bias, seed=seed))
        rv_deg = np.degrees(Rotation.from_quat(meas.q_xyzw[[k_quarter, k_end]]).as_rotvec())
        b_quarter.append(rv_deg[0])
        b_end.append(rv_deg[1])
    # 900 samples (300 seeds x 3 axes): std error of a variance ~5%
    var_quarter = np.var(np.concatenate(b_quarter))
    var_end = np.var(np.concatenate(b_end))
    assert abs(var_end / (bias**2 * 10.0) - 1.0) < 0.15, var_end
    assert abs(var_quarter / (bias**2 * 2.5) - 1.0) < 0.15, var_quarter
    assert abs(np.mean(np.concatenate(b_end))) < 3 * math.sqrt(bias**2 * 10.0 / 900)


def test_bias_starts_at_zero_and_drifts():
    t = np.arange(0.0, 60.0, 0.02)
    model = AttitudeErrorModel(bias_deg_per_sqrt_s=0.1, seed=4)
    meas = apply_error_model(_identity_truth(t), t, model)
    drift_deg = np.degrees(np.linalg.norm(Rotation.from_quat(meas.q_xyzw).as_rotvec(), axis=1))
    assert drift_deg[0] == 0.0
    # a random walk, not white noise: neighbouring samples nearly equal
    # per-axis step std 0.1 * sqrt(0.02) = 0.014 deg; white noise would jump by ~drift size
    assert np.max(np.abs(np.diff(drift_deg))) < 0.1
    assert drift_deg[-1] > 0.01


def test_same_seed_identical_different_seed_differs(rpy):
    model = AttitudeErrorModel(noise_deg=0.2, bias_deg_per_sqrt_s=0.05, offset_ms=5.0, seed=7)
    a, _ = attitude_for_replay(rpy, model)
    b, _ = attitude_for_replay(rpy, model)
    c, _ = attitude_for_replay(rpy, AttitudeErrorModel(noise_deg=0.2, bias_deg_per_sqrt_s=0.05,
                                                       offset_ms=5.0, seed=8))
    assert np.array_equal(a.trajectory.q_xyzw, b.trajectory.q_xyzw)
    assert np.array_equal(a.trajectory.t_s, c.trajectory.t_s)
    diff_deg = _angle_deg(Rotation.from_quat(a.trajectory.q_xyzw).as_matrix(),
                          Rotation.from_quat(c.trajectory.q_xyzw).as_matrix())
    assert np.median(diff_deg) > 0.05


def test_error_model_validation_and_is_zero():
    assert AttitudeErrorModel().is_zero
    assert AttitudeErrorModel(seed=5).is_zero
    assert not AttitudeErrorModel(offset_ms=1.0).is_zero
    assert not AttitudeErrorModel(noise_deg=0.1).is_zero
    assert not AttitudeErrorModel(bias_deg_per_sqrt_s=0.1).is_zero
    with pytest.raises(NislamError, match="noise_deg"):
        AttitudeErrorModel(noise_deg=-0.1)
    with pytest.raises(NislamError, match="offset_ms"):
        AttitudeErrorModel(offset_ms=float("nan"))


def test_series_with_one_or_no_sample():
    identity = np.array([[0.0, 0.0, 0.0, 1.0]])
    one = AttitudeSeries(Trajectory(np.array([2.0]), np.zeros((1, 3)), identity))
    np.testing.assert_allclose(one.rotation_at(2.0), np.eye(3))
    assert one.rotation_at(2.01) is None
    empty = AttitudeSeries(Trajectory(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4))))
    assert empty.rotation_at(0.0) is None and empty.span_s is None
