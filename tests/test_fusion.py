"""FusedTracker (onboard/fusion/fused.py): both trackers' motions in one filter,
a wild pose gated out, no jump and no reset when a tracker drops out and
comes back, and the covariance it reports (onboard/fusion/filter.py)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
from fake_results import track_result
from scipy.spatial.transform import Rotation

from onboard.app.health import HealthMonitor, HealthThresholds
from onboard.core.messages import Health, RgbdFrame, TrackResult
from onboard.fusion.coverage import sigma1_coverage
from onboard.fusion.filter import AnchoredFilter
from onboard.fusion.fused import GATED, FusedTracker
from onboard.fusion.measurements import fastorb_cov, nislam_cov
from onboard.fusion.params import FusionParams

DT = 1.0 / 30.0
SD_M = 0.001  # the fake trackers' position noise and what they report
VAR = np.array([SD_M**2] * 3 + [1e-5] * 3)


def truth(t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Swinging along x at up to 1 m/s while climbing and yawing."""
    return (np.array([np.sin(t_s), 0.3 * t_s, 0.1 * np.cos(2.0 * t_s)]),
            Rotation.from_euler("z", 40.0 * t_s, degrees=True).as_matrix())


class Attitude:
    def rotation_at(self, t_s: float) -> np.ndarray:
        return truth(t_s)[1]


# What a fake tracker reports at frame i: None (lost) or (world offset, keyframe id, resets).
Script = Callable[[int], tuple[np.ndarray, int, int] | None]


class Scripted:
    """A tracker reporting the truth plus noise, shifted by the script's world offset."""

    def __init__(self, name: str, script: Script, seed: int, noise_sd_m: float = SD_M) -> None:
        self.name = name
        self.noise_sd_m = noise_sd_m
        self.script = script
        self.rng = np.random.default_rng(seed)
        self.i = 0

    def track(self, frame: RgbdFrame, attitude: Attitude) -> TrackResult:
        i, self.i = self.i, self.i + 1
        s = self.script(i)
        if s is None:
            return track_result(frame.t_s, trusted=False, lost_reason="too few inliers")
        offset, key, resets = s
        p, R = truth(frame.t_s)
        p = p + offset + self.rng.normal(0.0, self.noise_sd_m, 3)
        return track_result(frame.t_s, p, R, pose_var=VAR, keyframe_id=key, reset_counter=resets,
                            psr=float("nan"))

    def finish(self) -> None:
        return None


def steady(i: int) -> tuple[np.ndarray, int, int]:
    return np.zeros(3), i // 10, 0


def run(a: Script, b: Script, n: int = 150) -> tuple[FusedTracker, list[TrackResult]]:
    fused = FusedTracker([Scripted("nislam", a, 1), Scripted("fastorb", b, 2)], FusionParams())
    img = np.zeros((4, 4, 3), np.uint8)
    depth = np.zeros((4, 4), np.float32)
    return fused, [fused.track(RgbdFrame(i * DT, img, depth), Attitude()) for i in range(n)]


def errors(results: list[TrackResult]) -> np.ndarray:
    """Position error against the truth, both measured from the first frame."""
    p0 = truth(results[0].t_s)[0]
    return np.array([np.linalg.norm(r.p_W_m - (truth(r.t_s)[0] - p0)) for r in results])


def steps(results: list[TrackResult]) -> np.ndarray:
    """How far each output step differs from the true step."""
    e = np.array([r.p_W_m - truth(r.t_s)[0] for r in results])
    return np.linalg.norm(np.diff(e, axis=0), axis=1)


def test_a_wild_pose_is_gated_out_and_the_tracker_tied_back_in() -> None:
    # FastORB jumps 0.3 m at frame 40 (a wrong re-localisation, no reset
    # reported) and keeps that world: that frame is left out by the gate and
    # the tracker goes on from there (its later motion is right again).
    def jumpy(i: int) -> tuple[np.ndarray, int, int]:
        return (np.array([0.3, 0.0, 0.0]) if i >= 40 else np.zeros(3)), i // 10, 0

    fused, results = run(steady, jumpy)
    assert all(r.trusted for r in results)
    assert results[-1].reset_counter == 0
    assert errors(results).max() < 0.01  # never pulled towards the wild pose
    fo = fused.stats()["trackers"]["fastorb"]
    assert fo["left_out"] == {GATED: 1}
    assert fo["reanchored"] == {"joined": 1, "disagreed": 1}
    assert fo["frames_used"] == 150 - 2  # all but its first (joined) and the jump
    left = results[40].left_out
    assert left and left[0][0] == "fastorb" and left[0][1].startswith(GATED)
    assert results[40].contributors == ("nislam",)
    assert results[41].contributors == ("nislam", "fastorb")


def test_a_tracker_going_wild_within_the_loose_prediction_is_left_out() -> None:
    # FastORB drifts 3-6 cm off over three frames before it recovers (as it
    # does before it reports lost): each step is within the prediction's
    # gate (the motion model allows cm per frame), but far from NI-SLAM.
    def wild(i: int) -> tuple[np.ndarray, int, int]:
        off = {40: 0.03, 41: 0.05, 42: 0.06}.get(i, 0.0)
        return np.array([off, 0.0, 0.0]), i // 10, 0

    fused, results = run(steady, wild)
    assert errors(results).max() < 0.005  # not pulled towards the wild poses
    assert fused.stats()["trackers"]["fastorb"]["left_out"][GATED] >= 2
    assert all(r.reset_counter == 0 for r in results)
    assert steps(results).max() < 0.005


def test_output_does_not_jump_when_a_tracker_drops_out_and_comes_back() -> None:
    # NI-SLAM lost for frames 30-59, back restarted in a shifted world (own
    # reset); FastORB lost for frames 90-119 and re-initialised at its origin.
    def nislam(i: int) -> tuple[np.ndarray, int, int] | None:
        if 30 <= i < 60:
            return None
        return (np.array([0.5, -0.2, 0.1]) if i >= 60 else np.zeros(3)), i // 10, int(i >= 60)

    def fastorb(i: int) -> tuple[np.ndarray, int, int] | None:
        if 90 <= i < 120:
            return None
        return (-truth(120 * DT)[0] if i >= 120 else np.zeros(3)), i // 7, int(i >= 120)

    fused, results = run(nislam, fastorb)
    assert all(r.trusted for r in results)
    assert {r.reset_counter for r in results} == {0}
    assert steps(results).max() < 0.008  # the trackers' mm of noise, no jump (offsets: 0.1-1 m)
    assert errors(results).max() < 0.01
    assert results[45].contributors == ("fastorb",)
    assert results[45].left_out == (("nislam", "lost: too few inliers"),)
    assert results[100].contributors == ("nislam",)
    stats = fused.stats()["trackers"]
    assert stats["nislam"]["left_out"]["lost: too few inliers"] == 30
    # Back in a shifted world: out of the gate, so tied back in at once.
    assert stats["nislam"]["reanchored"] == {"joined": 1, "restarted": 1}
    assert stats["nislam"]["left_out"]["restarted"] == 1
    assert stats["fastorb"]["left_out"]["lost: too few inliers"] == 30
    assert stats["fastorb"]["reanchored"] == {"joined": 1, "restarted": 1}


def test_a_relocalised_tracker_is_tied_back_in_without_its_jump() -> None:
    # FastORB re-localises into its map after a lost spell (its reset counter
    # moves) 4 cm off where it left: inside the gate, but a correction of its
    # world, not motion; the fused output must not take it.
    def reloc(i: int) -> tuple[np.ndarray, int, int] | None:
        if 40 <= i < 50:
            return None
        return (np.array([0.0, 0.04, 0.0]) if i >= 50 else np.zeros(3)), i // 10, int(i >= 50)

    fused, results = run(steady, reloc, 80)
    fo = fused.stats()["trackers"]["fastorb"]
    assert fo["reanchored"] == {"joined": 1, "restarted": 1}
    assert fo["frames_used"] == 80 - 1 - 10 - 1
    assert results[50].left_out == (("fastorb", "restarted"),)
    assert results[51].contributors == ("nislam", "fastorb")
    assert steps(results).max() < 0.005 and errors(results).max() < 0.005


class KeyedTracker:
    """NI-SLAM-like: poses relative to a key (`reference_offset_m`), the frame
    that weakens the match (every 10th) becoming the next key, and at frame 60
    the kept key made at frame 9 re-used, its position moved by `correction`
    by the key map since: p_W_m jumps by that much, the offset does not."""

    name = "nislam"

    def __init__(self, correction: np.ndarray) -> None:
        self.correction = correction
        self.rng = np.random.default_rng(4)
        self.keys: dict[int, tuple[np.ndarray, int]] = {0: (np.zeros(3), 0)}  # id: (p_W, frame)
        self.ref = 0
        self.i = 0

    def track(self, frame: RgbdFrame, attitude: Attitude) -> TrackResult:
        i, self.i = self.i, self.i + 1
        p, R = truth(frame.t_s)
        if i == 60:
            self.ref = 1
            self.keys[1] = (self.keys[1][0] + self.correction, self.keys[1][1])
        key_p, key_frame = self.keys[self.ref]
        d = p - truth(key_frame * DT)[0] + self.rng.normal(0.0, SD_M, 3)
        r = dataclasses.replace(
            track_result(frame.t_s, key_p + d, R, pose_var=VAR, keyframe_id=self.ref, psr=float("nan")),
            reference_keyframe_id=self.ref, reference_offset_m=d, keyframe_reused=i == 60)
        if i % 10 == 9:
            self.ref = len(self.keys)
            self.keys[self.ref] = (key_p + d, i)
            r = dataclasses.replace(r, keyframe_id=self.ref, new_keyframe=True)
        return r

    def finish(self) -> None:
        return None


def run_keyed(params: FusionParams | None = None) -> tuple[FusedTracker, list[TrackResult]]:
    nislam = KeyedTracker(np.array([0.04, 0.0, 0.0]))
    fused = FusedTracker([nislam, Scripted("fastorb", lambda i: None, 2)], params or FusionParams())
    img, depth = np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4), np.float32)
    return fused, [fused.track(RgbdFrame(i * DT, img, depth), Attitude()) for i in range(100)]


def test_a_re_used_key_closes_the_loop_without_its_jump() -> None:
    # NI-SLAM's position jumps 4 cm where it re-uses a kept key (inside the
    # gate): the fused output follows its motion relative to each key, and on
    # the re-used key its offset to that key's fused clone, never the jump.
    fused, results = run_keyed()
    assert all(r.trusted for r in results) and results[-1].reset_counter == 0
    assert steps(results).max() < 0.006
    e = errors(results)
    assert e.max() < 0.02  # keys' drift, 1 mm each; the offsets are 0.1-1 m
    assert e[60:70].max() < e[50:60].max()  # back on key 1: the drift since is taken out
    ni = fused.stats()["trackers"]["nislam"]
    assert ni["left_out"] == {} and ni["frames_used"] == 100 - 1
    assert results[60].contributors == ("nislam",)


def test_a_re_used_key_without_its_clone_only_ties_the_tracker_in() -> None:
    # One clone kept: key 1's is gone by frame 60, so the re-used key's frame
    # carries no motion (its jump is not taken) and the tracker goes on from there.
    fused, results = run_keyed(dataclasses.replace(FusionParams(), key_clones=1))
    assert steps(results).max() < 0.006 and errors(results).max() < 0.02
    ni = fused.stats()["trackers"]["nislam"]
    assert ni["left_out"] == {"key re-used": 1} and ni["frames_used"] == 100 - 2
    assert results[60].left_out[0] == ("nislam", "key re-used")


def test_without_either_tracker_it_coasts_then_is_lost_and_resets_once() -> None:
    def gap(i: int) -> tuple[np.ndarray, int, int] | None:
        return None if 50 <= i < 80 else (np.zeros(3), i // 10, 0)

    _, results = run(gap, gap, 120)
    coast = int(FusionParams().max_coast_s / DT)
    assert all(r.trusted for r in results[50:50 + coast])
    assert not any(r.trusted for r in results[50 + coast + 1:80])
    assert results[79].lost_reason.startswith("no tracker")
    assert [r.reset_counter for r in results[80:]] == [1] * 40


def test_filter_covariance_grows_with_each_anchor_and_is_consistent() -> None:
    # One tracker measuring motion since anchors re-set every 10 frames: the
    # position error is a random walk over the anchors, and the reported
    # sigma covers about 68 % of it (a consistent filter).
    rng = np.random.default_rng(3)
    inside, total = 0, 0
    for run_i in range(40):
        f = AnchoredFilter(1, accel_sd_m_s2=1.0)
        f.start(0.0, np.zeros(3), 0.0, 0.5)
        p_true = np.zeros(3)
        anchor_true = np.zeros(3)
        v = rng.normal(0.0, 0.3, 3)
        for k in range(1, 101):
            p_true = p_true + v * DT
            f.predict(k * DT)
            R = np.eye(3) * SD_M**2
            f.update(0, p_true - anchor_true + rng.normal(0.0, SD_M, 3), R)
            if k % 10 == 0:
                f.anchor(0)
                anchor_true = p_true.copy()
        inside += int(np.sum(np.abs(f.p - p_true) <= np.sqrt(np.diag(f.P_pp))))
        total += 3
    assert 0.55 <= inside / total <= 0.8
    assert np.sqrt(np.diag(f.P_pp)).min() > 2.5 * SD_M  # ten anchors: ~sqrt(10) sd


def test_covariances_scale_up_when_the_trackers_disagree_more_than_they_claim() -> None:
    # Both trackers report 1 mm but err by 3 mm (real data: a depth sensor's
    # distortion their quality signals do not see): the scale on their
    # covariances rises several times (towards 3^2: part of each motion's
    # error is in its anchor, which the fused clone holds); honest ones keep theirs.
    img, depth = np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4), np.float32)
    scales = []
    for sd in (SD_M, 3 * SD_M):
        fused = FusedTracker([Scripted("nislam", steady, 1, sd), Scripted("fastorb", steady, 2, sd)])
        for i in range(400):
            fused.track(RgbdFrame(i * DT, img, depth), Attitude())
        scales.append(fused.noise_scale)
    assert scales[0] < 1.5
    assert 3.0 < scales[1] < 15.0


def test_sigma1_coverage_counts_axes_within_one_sigma() -> None:
    p_true = np.zeros((4, 3))
    p_est = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.3, 0], [0, 0, 0]], dtype=float)
    var = np.full((4, 3), 0.2**2)
    assert sigma1_coverage(p_est, var, p_true) == 11 / 12
    assert sigma1_coverage(p_est[:0], var[:0], p_true[:0]) is None


def test_health_says_which_trackers_the_pose_used_and_why_one_is_left_out() -> None:
    _, results = run(steady, lambda i: None if i >= 5 else steady(i), 10)
    th = HealthThresholds(frame_timeout_s=0.5, degraded_gap_s=0.2, degraded_quality=5,
                          start_grace_s=5.0, recover_s=0.0)
    monitor = HealthMonitor(th, 0.0)
    both = monitor.on_frame(0.1, results[2], None)
    assert both.state is Health.TRACKING and both.reason.endswith("; nislam+fastorb")
    one = monitor.on_frame(0.2, results[7], None)
    assert one.state is Health.TRACKING
    assert one.reason.endswith("; nislam only; fastorb: lost: too few inliers")


def test_measurement_covariances_follow_each_trackers_quality_signals() -> None:
    p = FusionParams()
    # Camera looking along world x: its optical axis (NI-SLAM's depth step) is x.
    R = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    var_W = np.array([0.02**2, 0.01**2, 0.01**2, 1e-5, 1e-5, 1e-5])  # depth scatter 2 cm on x
    firm = dataclasses.replace(track_result(0.0, np.zeros(3), R, pose_var=var_W, psr=p.psr_full),
                               res_m=0.01, matched_cells=4096)
    base = np.diag(nislam_cov(firm, p))
    weak = np.diag(nislam_cov(dataclasses.replace(firm, psr=p.psr_full / 3), p))
    few = np.diag(nislam_cov(dataclasses.replace(firm, matched_cells=256), p))
    assert np.allclose(base[1:], (p.nislam_peak_cells * 0.01) ** 2)  # lateral: the peak
    assert np.isclose(base[0], 0.02**2 * p.nislam_cells_per_sample / 4096)  # depth: the mean
    assert np.allclose(weak[1:], 9 * base[1:]) and np.isclose(weak[0], base[0])
    assert np.isclose(few[0], 16 * base[0]) and np.allclose(few[1:], base[1:])
    fo = dataclasses.replace(track_result(0.0, pose_var=np.full(6, 0.002**2)), matched_cells=300)
    assert np.allclose(np.diag(fastorb_cov(fo, p)), 0.002**2 * p.fastorb_var_scale)
    thin = dataclasses.replace(fo, matched_cells=p.fastorb_full_inliers // 3)
    assert np.allclose(np.diag(fastorb_cov(thin, p)), 9 * 0.002**2 * p.fastorb_var_scale)
