"""The ODOMETRY velocity's covariance is that of the displacement it is
differenced from (onboard.outputs.mavlink_feed._twist, the fused tracker's
clones in onboard.fusion.displacement), not the sum of two absolute position
variances: over a long flight the fused position's variance grows with the
drift while the velocity's must stay as it is and cover the true error."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from fake_results import track_result
from test_fusion import DT, Attitude, truth
from test_fusion_coverage import Drifting

from onboard.core.messages import RgbdFrame
from onboard.fusion.filter import AnchoredFilter
from onboard.fusion.fused import FusedTracker
from onboard.fusion.params import FusionParams
from onboard.outputs.mavlink_feed import VisionFeed, diag_cov21, odometry_args

WINDOW_S = 0.1


def fly(n: int, seed: int, params: FusionParams = FusionParams()) -> tuple[list, list]:
    """Two honest drifting fake trackers fused, then fed: (results, samples)."""
    trackers = [Drifting("a", 0.002, 0.002, 7, 10 * seed + 1),
                Drifting("b", 0.003, 0.003, 11, 10 * seed + 2)]
    fused = FusedTracker(trackers, params)  # type: ignore[arg-type]
    feed = VisionFeed(np.eye(3), velocity_window_s=WINDOW_S)
    img, depth = np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4), np.float32)
    results, samples = [], []
    for i in range(n):
        r = fused.track(RgbdFrame(i * DT, img, depth), Attitude())  # type: ignore[arg-type]
        results.append(r)
        samples.append(feed.update(r).sample)
    return results, samples


def displacement_errors(samples: list) -> tuple[np.ndarray, np.ndarray]:
    """(error of v * dt against the true displacement, claimed sd), per frame and
    axis, over the feed's window (3 frames at 30 Hz)."""
    lag = round(WINDOW_S / DT)
    e, sd = [], []
    for k in range(lag, len(samples)):
        s = samples[k]
        t1, t0 = k * DT, (k - lag) * DT
        dt = t1 - t0
        e.append(s.v_L_m_s * dt - (truth(t1)[0] - truth(t0)[0]))
        sd.append(np.sqrt(s.v_var_L) * dt)
    return np.array(e), np.array(sd)


def test_velocity_variance_stays_bounded_and_honest_while_the_position_variance_grows() -> None:
    n = 600  # 20 s; the fused position sd grows ~3x over it (a key every 7 and 11 frames)
    covered, first, last = [], [], []
    for seed in range(2):
        results, samples = fly(n, seed)
        pos_sd = np.sqrt([r.pose_var[0] for r in results])
        assert pos_sd[-30:].mean() > 2.5 * pos_sd[30:60].mean()  # the absolute variance grows
        e, sd = displacement_errors(samples)
        covered.append(np.mean(np.abs(e) <= sd))
        first.append(np.sqrt(np.mean(sd[60:210] ** 2)))  # after the start-up, 5 s
        last.append(np.sqrt(np.mean(sd[-150:] ** 2)))
    # With the two poses' summed absolute variances (the old formula) the sd
    # grew with the position's, ~3x, and covered ~100 % of the error.
    assert max(b / a for a, b in zip(first, last)) < 1.15
    assert 0.6 <= np.mean(covered) <= 0.76


def test_the_feed_takes_the_trackers_displacement_covariance_else_the_sum() -> None:
    feed = VisionFeed(np.eye(3), "flu", velocity_window_s=WINDOW_S)
    big = np.array([1.0, 1.0, 1.0, 1e-4, 1e-4, 1e-4])  # absolute: 1 m sd
    C = np.array([[4e-6, 1e-6, 0.0], [1e-6, 9e-6, 0.0], [0.0, 0.0, 1e-6]])
    r0 = track_result(0.0, [0.0, 0.0, 0.0], pose_var=big)
    r1 = dataclasses.replace(track_result(0.05, [0.01, 0.0, 0.0], pose_var=big),
                             displacement_cov=((0.0, C),))
    r2 = dataclasses.replace(track_result(0.1, [0.02, 0.0, 0.0], pose_var=big),
                             displacement_cov=((0.05, C),))  # not the pose the feed differences from
    assert np.isnan(feed.update(r0).sample.v_var_L).all()
    s1 = feed.update(r1).sample
    assert np.allclose(s1.v_var_L, np.diag(C) / 0.05**2)  # flu -> L: diag(1, -1, -1), same diagonal
    assert np.allclose(s1.twist_var_B, np.concatenate([np.diag(C) / 0.05**2, [0.08] * 3]))
    s2 = feed.update(r2).sample
    assert np.allclose(s2.v_var_L, 2.0 / 0.1**2)  # fallback: var_k + var_j


def test_a_restart_still_sends_an_unknown_velocity() -> None:
    """A lost spell of both trackers: the fused tracker restarts (reset
    counter + 1) and the feed's first pose after it carries NaN velocity and
    covariance, although the tracker's own clones are held again."""

    class Gap(Drifting):
        def track(self, frame, attitude):  # type: ignore[no-untyped-def]
            r = super().track(frame, attitude)
            if 60 <= self.i <= 70:
                return track_result(frame.t_s, trusted=False, lost_reason="blind")
            return r

    params = FusionParams()
    fused = FusedTracker([Gap("a", 0.002, 0.002, 7, 1), Gap("b", 0.003, 0.003, 11, 2)], params)  # type: ignore[arg-type]
    feed = VisionFeed(np.eye(3), velocity_window_s=WINDOW_S)
    img, depth = np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4), np.float32)
    out = []
    for i in range(90):
        r = fused.track(RgbdFrame(i * DT, img, depth), Attitude())  # type: ignore[arg-type]
        out.append((r, feed.update(r).sample))
    back = next(k for k, (r, _) in enumerate(out) if r.reset_counter == 1 and r.trusted)
    r, s = out[back]
    assert r.displacement_cov == ()  # the clones went with the restart
    assert np.isnan(s.v_L_m_s).all() and math.isnan(diag_cov21(s.twist_var_B)[0])
    assert math.isnan(odometry_args(s)[-4][0])  # ODOMETRY's velocity_covariance[0]
    r, s = out[back + 1]
    assert len(r.displacement_cov) == 1 and np.all(np.isfinite(s.v_var_L))
    assert np.all(s.v_var_L < 1e-2)  # from the clone: (a few mm / 33 ms)^2, not the absolute variance


def test_the_displacement_covariance_is_that_of_the_positions_put_out() -> None:
    """Monte Carlo on the filter alone (white acceleration, one anchor): the
    error of p_k minus the p_j put out at frame j has the covariance
    `displacement_cov` says. A clone kept as a state (its estimate corrected by
    the later updates, P's own blocks) says ~15 % less: that is the smoothed
    p_j's, not the one the feed differences from."""
    rng = np.random.default_rng(0)
    dt, q, r_sd = 1.0 / 30.0, 25.0, 0.01
    L = np.linalg.cholesky(q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]))
    errors, claimed = [], []
    for _ in range(2000):
        f = AnchoredFilter(1, math.sqrt(q), n_frozen=1)
        p, v = np.zeros(3), rng.normal(0.0, 0.5, 3)
        f.start(0.0, p, 0.0, 0.5)
        for k in range(1, 11):
            w = L @ rng.normal(size=(2, 3))
            p, v = p + v * dt + w[0], v + w[1]
            f.predict(k * dt)
            f.update(0, p + rng.normal(0.0, r_sd, 3), np.eye(3) * r_sd**2)  # anchor at the origin
            if k == 3:
                f.freeze(0)
                p_j, p_j_true = f.p, p.copy()
        errors.append((f.p - p_j) - (p - p_j_true))
        claimed.append(np.trace(f.displacement_cov(0)) / 3.0)
    assert abs(np.var(errors) / np.mean(claimed) - 1.0) < 0.1  # measured 0.95
