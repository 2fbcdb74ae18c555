"""The Kinect-like depth profile: errors in disparity, correlated over the
matching window and rounded to disparity steps (what a real RGB-D sensor's
depth has and the gaussian profile has not), chosen by name."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onboard import NislamError
from sim_replay.sensors import DEPTH_PROFILES, KINECT_V1, depth_profile, measure_depth
from sim_replay.sim import sim_options


def _tilted_plane(z0: float) -> np.ndarray:
    """A wall at z0 turned about the vertical axis: depth rises across the rows
    by about a tenth of a disparity step per pixel."""
    x = np.arange(240, dtype=np.float32)
    slope = 0.1 * float(KINECT_V1.depth_step_m(z0))
    return np.broadcast_to(z0 + slope * (x - 120), (180, 240)).astype(np.float32)


def _row_residual_corr(err: np.ndarray, lag: int) -> float:
    e = err - err.mean()
    return float(np.mean(e[:, :-lag] * e[:, lag:]) / np.mean(e * e))


@pytest.mark.parametrize("z0", [1.0, 3.0])
def test_kinect_depth_comes_in_disparity_steps_and_errs_in_patches(z0):
    truth = _tilted_plane(z0)
    fb = KINECT_V1.focal_px * KINECT_V1.baseline_m
    for name in ("kinect", "gaussian"):
        z = measure_depth(truth, depth_profile(name), np.random.default_rng(3)).astype(np.float64)
        assert (z > 0).all()
        steps = fb / z / KINECT_V1.subpixel_px  # whole numbers for a disparity sensor
        on_step = np.abs(steps - np.rint(steps)) < 1e-3
        err = z - truth
        if name == "kinect":
            assert on_step.all()
            # neighbours 4 px apart share most of their error (9 px window);
            # 16 px apart nothing
            assert _row_residual_corr(err, 4) > 0.25
            assert abs(_row_residual_corr(err, 16)) < 0.1
            # the error is the sensor's: sd of ~0.6-0.7 steps (noise + rounding)
            sd_steps = err.std() / float(KINECT_V1.depth_step_m(z0))
            assert 0.5 < sd_steps < 0.8, sd_steps
        else:  # the gaussian profile: neither
            assert on_step.mean() < 0.05
            assert abs(_row_residual_corr(err, 4)) < 0.1


def test_depth_step_grows_with_the_square_of_depth():
    assert KINECT_V1.depth_step_m(1.0) == pytest.approx(0.125 / (580 * 0.075))
    assert KINECT_V1.depth_step_m(3.0) == pytest.approx(9 * KINECT_V1.depth_step_m(1.0))


def test_profiles_draw_alike_and_are_chosen_by_name():
    truth = _tilted_plane(2.0)
    states = []
    for name in DEPTH_PROFILES:
        rng = np.random.default_rng(5)
        measure_depth(truth, DEPTH_PROFILES[name], rng)
        states.append(rng.integers(1 << 62))  # the colour noise draws next
    assert len(set(states)) == 1
    assert sim_options(depth_profile_name="kinect").depth.disparity == KINECT_V1
    assert sim_options().depth == DEPTH_PROFILES["gaussian"]
    with pytest.raises(NislamError, match="unknown depth profile"):
        sim_options(depth_profile_name="lidar")
    with pytest.raises(NislamError, match="ideal-camera"):
        sim_options(ideal_camera=True, depth_profile_name="kinect")
    assert math.isfinite(DEPTH_PROFILES["kinect"].max_range_m)
