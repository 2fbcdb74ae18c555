"""Capture times from host stamps (sim_replay/stamps.py)."""

import numpy as np

from sim_replay.stamps import fit_camera_clock

PERIOD_S = 1 / 30.0


def _clock(n: int, t0: float = 1000.0, period: float = PERIOD_S) -> np.ndarray:
    return t0 + period * np.arange(n)


def test_jittered_stamps_come_back_to_the_clock_with_drops_and_a_jump():
    rng = np.random.default_rng(3)
    true_t = np.concatenate((_clock(400), _clock(300, t0=1030.0, period=PERIOD_S * 1.001)))
    keep = np.ones(len(true_t), bool)
    keep[[50, 51, 52, 200, 550]] = False  # dropped frames: the index must count them
    true_t = true_t[keep]
    # Host delay: 4 ms constant + 1.5 ms RMS jitter, one 15 ms USB stall.
    stamps = true_t + 0.004 + rng.normal(0.0, 0.0015, len(true_t))
    stamps[120] += 0.015
    fit = fit_camera_clock(stamps, window_s=1.0)
    err_ms = (fit.t_s - true_t - 0.004) * 1e3
    assert fit.frames_fitted == len(stamps)
    assert abs(fit.period_ms - PERIOD_S * 1e3) < 0.05
    assert np.sqrt(np.mean(err_ms ** 2)) < 0.4  # from 1.5 ms RMS
    assert np.abs(err_ms).max() < 1.5  # the stall too, and across the drops and the jump
    assert 1.2 < fit.residual_rms_ms < 2.0
    assert np.all(np.diff(fit.t_s) > 0)


def test_exact_stamps_stay_bit_exact_and_off_means_off():
    t = _clock(300)
    assert np.array_equal(fit_camera_clock(t).t_s, t)
    assert fit_camera_clock(t).frames_fitted == 0
    jittered = t + np.random.default_rng(0).normal(0.0, 0.001, len(t))
    assert np.array_equal(fit_camera_clock(jittered, window_s=0.0).t_s, jittered)


def test_a_variable_rate_stream_keeps_its_stamps():
    rng = np.random.default_rng(1)
    t = 50.0 + np.cumsum(rng.uniform(0.02, 0.09, 300))  # no fixed clock behind it
    fit = fit_camera_clock(t)
    assert fit.frames_fitted == 0 and np.array_equal(fit.t_s, t)
    assert fit.describe() == "stamps as recorded"
