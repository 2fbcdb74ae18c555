"""FastORB's per-frame cost cuts compute what the tracker computed before:
the compiled refinement loops equal their numpy references on random
problems, and the key-frame work done after the pose (`finish_frame`)
gives the poses of the work done in place."""

from __future__ import annotations

import numpy as np
import pytest
from test_fastorb import DT, INTR, K, NoAttitude, Room, _random_twist, flight

from onboard.core.messages import RgbdFrame
from onboard.core.se3 import se3_exp
from onboard.fastorb import pose, shutter
from onboard.fastorb.params import FastOrbParams
from onboard.fastorb.refine_kernels import gate_px, se3_exp_left
from onboard.fastorb.tracker import FastOrbTracker


def _problem(rng: np.random.Generator, n: int = 300):
    """Landmarks 1-4 m away seen under a true pose, pixels with 0.5 px noise
    and 5 % gross outliers, disparities (bf = 120) on 80 % of them, and a
    start 1-2 cm / ~1 deg off."""
    obj = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(1, 4, n)])
    T_true = se3_exp(_random_twist(rng, 0.05, 0.05))
    p = obj @ T_true[:3, :3].T + T_true[:3, 3]
    img = np.column_stack([K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2],
                           K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]])
    img += rng.normal(0, 0.5, (n, 2))
    img[: n // 20] += rng.uniform(-8, 8, (n // 20, 2))
    disp = np.where(rng.uniform(size=n) < 0.8, 120.0 / p[:, 2] + rng.normal(0, 0.3, n), 0.0)
    start = se3_exp(_random_twist(rng, 0.02, 0.02)) @ T_true
    return obj, img, disp, start, T_true


def test_compiled_se3_step_equals_se3_exp() -> None:
    rng = np.random.default_rng(21)
    for scale in (1e-9, 1e-7, 1e-3, 0.5, 2.0):
        xi = rng.normal(0, scale, 6)
        T = se3_exp(rng.normal(0, 0.3, 6))
        np.testing.assert_allclose(se3_exp_left(xi, T), se3_exp(xi) @ T, rtol=0, atol=1e-14)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compiled_pose_refinement_equals_numpy_loop(seed: int) -> None:
    """refine_pose (compiled loop) = its numpy loop to rounding, for Huber
    with and without disparities and a selection; both reach the truth."""
    rng = np.random.default_rng(seed)
    obj, img, disp, start, T_true = _problem(rng)
    sel = rng.uniform(size=len(obj)) < 0.9
    for bf, huber, iters in ((120.0, 1.0, 4), (0.0, 1.0, 4), (120.0, 0.0, 1)):
        got = pose.refine_pose(start, obj, img, K, huber, iters, disp, bf, sel)
        ref = pose._refine_pose_numpy(start, obj, img, disp, sel, K, bf, huber, iters)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
        assert not np.allclose(got, start, atol=1e-6)  # it did move
    got = pose.refine_pose(start, obj, img, K, 1.0, 10, disp, 120.0, sel)
    assert np.abs(got[:3, 3] - T_true[:3, 3]).max() < 2e-3
    # Nothing selected: a singular system, the start comes back (as numpy's LinAlgError)
    none = np.zeros(len(obj), bool)
    np.testing.assert_array_equal(pose.refine_pose(start, obj, img, K, 1.0, 4, disp, 120.0, none),
                                  start)


@pytest.mark.parametrize("seed", [3, 4])
def test_compiled_rate_fit_equals_numpy_loop(seed: int) -> None:
    """shutter.refine_with_rate (compiled) = its numpy loop: the pose and the
    body rate, with a rate prior far from and near the answer."""
    rng = np.random.default_rng(seed)
    obj, img, disp, start, _ = _problem(rng)
    for xi_prior in (rng.normal(0, 0.5, 6), np.zeros(6)):
        for bf in (120.0, 0.0):
            args = (obj, img, disp, K, bf, 1.0, 0.028, INTR.height, xi_prior, 0.5)
            T, w = shutter.refine_with_rate(start, *args)
            T_ref, w_ref = shutter._refine_with_rate_numpy(start, *args)
            np.testing.assert_allclose(T, T_ref, rtol=0, atol=1e-12)
            np.testing.assert_allclose(w, w_ref, rtol=0, atol=1e-10)
            assert np.abs(w - xi_prior[:3]).max() > 1e-4  # the fit moved the rate


def test_compiled_gate_equals_numpy_gate() -> None:
    rng = np.random.default_rng(5)
    s = pose.PnpSettings(reprojection_px=3.0, sigma_gate=3.0, min_gate_px=1.5)
    for n in (0, 1, 2, 7, 300):
        err = rng.gamma(2.0, 0.4, n)
        inl = rng.uniform(size=n) < 0.7
        assert gate_px(err, inl, 3.0, 1.5, 3.0) == pose._gate(err[inl], s)
    err = rng.gamma(2.0, 0.1, 50)  # tight residuals: the floor
    assert gate_px(err, np.ones(50, bool), 3.0, 1.5, 3.0) == 1.5 == pose._gate(err, s)


def test_keyframe_work_after_the_pose_changes_no_pose() -> None:
    """A key frame's making waits for finish_frame(): the result already
    names the new key frame, the local map gets it only after; a caller that
    never calls finish_frame() (the next track() runs it) gets the same poses
    and key frames bit for bit."""
    room = Room(seed=3)
    frames = [RgbdFrame(k * DT, *room.render(R, c)) for k, (R, c) in enumerate(flight(14))]
    params = FastOrbParams(keyframe_max_frames=4)
    a, b = FastOrbTracker(INTR, params), FastOrbTracker(INTR, params)
    keys = 0
    for f in frames[:14]:
        ra = a.track(f, NoAttitude())
        rb = b.track(f, NoAttitude())
        if ra.new_keyframe and keys:  # (the first key frame is made in place)
            assert a._map.newest.keyframe_id == ra.keyframe_id - 1  # queued, not made
            a.finish_frame()
            assert a._map.newest.keyframe_id == ra.keyframe_id
        keys += ra.new_keyframe
        a.finish_frame()
        np.testing.assert_array_equal(ra.p_W_m, rb.p_W_m)
        np.testing.assert_array_equal(ra.R_W_C, rb.R_W_C)
        assert (ra.keyframe_id, ra.new_keyframe, ra.matched_cells) == (
            rb.keyframe_id, rb.new_keyframe, rb.matched_cells)
        assert [c.keyframe_id for c in ra.finished_keyframes] == [
            c.keyframe_id for c in rb.finished_keyframes]
    assert keys >= 3


def test_shutter_points_equal_the_cross_product_form() -> None:
    """points_at_mid's written-out omega x p is np.cross's, bit for bit."""
    rng = np.random.default_rng(6)
    uv, z, xi = rng.uniform(0, 640, (200, 2)), rng.uniform(0.5, 4.0, 200), rng.normal(0, 1, 6)
    p = shutter.points_at_mid(uv, z, K, np.zeros(6), 0.028, INTR.height)  # no motion: as seen
    tau = shutter.row_times(uv[:, 1], 0.028, INTR.height)[:, None]
    np.testing.assert_array_equal(shutter.points_at_mid(uv, z, K, xi, 0.028, INTR.height),
                                  p - tau * (np.cross(xi[:3], p) + xi[3:]))

