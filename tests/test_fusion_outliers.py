"""The fused tracker's outlier check against the other tracker
(onboard/fusion/agreement.py): its bound is k F(k, nu) times the estimated
scale of the disagreement, so honest disagreement is not taken for an
outlier while that scale is still being learnt, and a wild pose still is."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.stats import chi2, f

from onboard.core.messages import RgbdFrame
from onboard.fusion.agreement import OutlierCheck
from onboard.fusion.fused import GATED, FusedTracker
from onboard.fusion.params import FusionParams
from test_fusion import DT, SD_M, Attitude, Scripted, errors, steady


def test_the_bound_is_the_predictive_one_and_tends_to_the_chi_square_bound() -> None:
    check = OutlierCheck(12.0, prior_dof=3.0, forget=0.0)
    tail = chi2.sf(12.0, 3)
    assert abs(check.bound() - 3.0 * f.isf(tail, 3, 3)) < 1e-6 * check.bound()
    assert check.bound() > 100.0  # one frame's worth known of the scale: very wide
    rng = np.random.default_rng(0)
    for d2 in rng.chisquare(3, 2000):  # disagreements as the covariances claim
        check.check(float(d2))
    assert 0.9 < check.scale < 1.1
    assert 12.0 <= check.bound() < 12.2  # chi2(3) 99.3 % again


def test_the_bound_follows_a_scale_larger_than_claimed_and_never_tightens_below_chi2() -> None:
    rng = np.random.default_rng(1)
    big, small = OutlierCheck(12.0, 3.0, 0.02), OutlierCheck(12.0, 3.0, 0.02)
    out_big = [big.check(float(6.0 * d2)) for d2 in rng.chisquare(3, 300)]
    out_small = [small.check(float(0.2 * d2)) for d2 in rng.chisquare(3, 300)]
    assert 4.5 < big.scale < 8.0 and sum(out_big) <= 6  # ~0.7 % of honest frames
    assert small.scale == 1.0 and small.bound() >= 12.0  # the trackers' figures are a floor
    assert not any(out_small)


def test_a_wild_pose_is_an_outlier_even_at_the_start_and_counts_only_as_the_bound() -> None:
    check = OutlierCheck(12.0, 3.0, 0.02)
    b0 = check.bound()
    assert check.check(1e4)  # far beyond: gated with nothing learnt yet
    assert check.scale == (3.0 * 0.98 + b0) / (3.0 * 0.98 + 3.0)  # censored at the bound, not 1e4
    for d2 in np.random.default_rng(2).chisquare(3, 60):
        check.check(float(d2))
    b = check.bound()
    assert b < 20.0
    assert check.check(300.0)  # 3 cm against 1-2 mm: still gated
    assert check.bound() < 1.2 * b  # counted as the bound (300 would take it to ~3 b)


def _run(a_sd: float, b_sd: float, params: FusionParams, n: int = 60) -> tuple[FusedTracker, list]:
    fused = FusedTracker([Scripted("nislam", steady, 1, a_sd), Scripted("fastorb", steady, 2, b_sd)], params)
    img, depth = np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4), np.float32)
    return fused, [fused.track(RgbdFrame(i * DT, img, depth), Attitude()) for i in range(n)]


def test_early_honest_disagreement_is_not_taken_for_outliers() -> None:
    # Both trackers err 4x what they claim (`tum_fr1_rpy`: real data adds what
    # their quality signals do not see). While the agreement scale climbs
    # from 1, their disagreements are honest, not wild: the check must not
    # re-tie a tracker (each NI-SLAM re-tie drops its key's clone and puts
    # that frame's error on the new anchor) and leaves out about its 0.7 %.
    # The fixed chi-square bound (the old rule; here a prior worth 1e12 dof)
    # leaves out 14 of the first 60 frames and re-ties three times.
    new = FusionParams()
    fused, out = _run(4 * SD_M, 4 * SD_M, new)
    stats = fused.stats()["trackers"]
    assert all(stats[n]["reanchored"].get("disagreed", 0) == 0 for n in ("nislam", "fastorb"))
    assert sum(stats[n]["left_out"].get(GATED, 0) for n in ("nislam", "fastorb")) <= 4
    assert all(r.trusted and r.reset_counter == 0 for r in out)

    old, old_out = _run(4 * SD_M, 4 * SD_M, dataclasses.replace(new, outlier_prior_dof=1e12))
    old_stats = old.stats()["trackers"]
    assert sum(old_stats[n]["left_out"].get(GATED, 0) for n in ("nislam", "fastorb")) >= 10
    assert sum(old_stats[n]["reanchored"].get("disagreed", 0) for n in ("nislam", "fastorb")) >= 2
    assert errors(out).max() < 0.8 * errors(old_out).max()


def test_a_wild_pose_at_the_third_frame_is_still_left_out() -> None:
    # The check's bound is widest at the start (nothing learnt of the
    # disagreement's scale), yet FastORB 3-6 cm off against ~1 mm sds is
    # far beyond it: not pulled towards the wild poses, as at frame 40
    # (test_fusion.test_a_tracker_going_wild_within_the_loose_prediction_is_left_out).
    def wild(i: int) -> tuple[np.ndarray, int, int]:
        off = {3: 0.03, 4: 0.05, 5: 0.06}.get(i, 0.0)
        return np.array([off, 0.0, 0.0]), i // 10, 0

    fused = FusedTracker([Scripted("nislam", steady, 1), Scripted("fastorb", wild, 2)], FusionParams())
    img, depth = np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4), np.float32)
    out = [fused.track(RgbdFrame(i * DT, img, depth), Attitude()) for i in range(30)]
    assert errors(out).max() < 0.005
    assert fused.stats()["trackers"]["fastorb"]["left_out"][GATED] >= 3
