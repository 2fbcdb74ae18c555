"""Frame-lag RPE against evo's own code, path length ratio and key-change jumps."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from onboard.core.evaluation import (
    RPE_LAGS_FRAMES,
    evaluate,
    lag_metrics,
    rpe_pairs_by_frames,
)
from onboard.core.trajectory import Trajectory

N = 120


def _pair(seed: int = 0) -> tuple[Trajectory, Trajectory]:
    """A turning, climbing ground truth and an estimate in another world frame
    with per-frame position and attitude noise."""
    rng = np.random.default_rng(seed)
    t = 1000.0 + np.arange(N) / 30.0
    ph = (t - t[0]) / 2.0
    p_gt = np.stack([np.cos(ph), 0.8 * np.sin(ph), 0.1 * ph], axis=1)
    r_gt = Rotation.from_euler("zyx", np.stack([ph, 0.2 * np.sin(2 * ph), 0.05 * ph], axis=1))
    r_w = Rotation.from_euler("zyx", [0.4, -0.3, 0.2])
    p_est = r_w.apply(p_gt + rng.normal(0.0, 0.004, (N, 3))) + [1.0, 2.0, -0.5]
    r_est = r_w * r_gt * Rotation.from_rotvec(rng.normal(0.0, 0.003, (N, 3)))
    return Trajectory(t, p_gt, r_gt.as_quat()), Trajectory(t, p_est, r_est.as_quat())


def _evo_rpe(gt: Trajectory, est: Trajectory, lag: int, relation: str, all_pairs: bool) -> float:
    from evo.core import metrics
    from evo.core.trajectory import PoseTrajectory3D

    def traj(x: Trajectory) -> PoseTrajectory3D:
        return PoseTrajectory3D(x.p_xyz_m, np.roll(x.q_xyzw, 1, axis=1), x.t_s)

    rel = {"trans": metrics.PoseRelation.translation_part,
           "deg": metrics.PoseRelation.rotation_angle_deg}[relation]
    rpe = metrics.RPE(rel, delta=lag, delta_unit=metrics.Unit.frames, all_pairs=all_pairs)
    rpe.process_data((traj(gt), traj(est)))
    return float(rpe.get_statistic(metrics.StatisticsType.rmse))


def test_lag_rpe_matches_evo() -> None:
    """`evo_rpe tum GT EST --delta K --delta_unit f -r trans_part --all_pairs`
    (evo's own classes, not a re-derivation) to 1e-6 for every lag."""
    gt, est = _pair()
    m = evaluate(est, gt)
    for lag in RPE_LAGS_FRAMES:
        ours = getattr(m, f"rpe_lag{lag}_m")
        assert ours > 1e-3  # vacuous on a perfect estimate
        assert ours == pytest.approx(_evo_rpe(gt, est, lag, "trans", True), abs=1e-6)
    assert m.rpe_rot_lag1_deg == pytest.approx(_evo_rpe(gt, est, 1, "deg", True), abs=1e-6)
    # The chained pairing (evo without --all_pairs) is evo's too.
    from onboard.core.evaluation import relative_pose_errors, rmse

    trans, _ = relative_pose_errors(est, gt, rpe_pairs_by_frames(N, 10, all_pairs=False))
    assert rmse(trans) == pytest.approx(_evo_rpe(gt, est, 10, "trans", False), abs=1e-6)
    assert m.as_dict()["rpe_lag30_m"] == pytest.approx(m.rpe_lag30_m)


def test_path_length_ratio_counts_jitter() -> None:
    gt, _ = _pair()
    r_w = Rotation.from_rotvec([0.1, 0.2, 0.3])
    moved = Trajectory(gt.t_s, r_w.apply(gt.p_xyz_m) + 3.0, gt.q_xyzw)
    assert lag_metrics(moved, gt)["path_length_ratio"] == pytest.approx(1.0, abs=1e-12)
    # 1 mm steps along x with a +-0.5 mm zig-zag across: every step sqrt(2) mm.
    t = np.arange(11) / 30.0
    q = np.tile([0.0, 0.0, 0.0, 1.0], (11, 1))
    truth = Trajectory(t, np.stack([t * 0.03, 0 * t, 0 * t], axis=1), q)
    zig = truth.p_xyz_m + np.stack([0 * t, 0.0005 * (-1.0) ** np.arange(11), 0 * t], axis=1)
    out = lag_metrics(Trajectory(t, zig, q), truth)
    assert out["path_length_ratio"] == pytest.approx(np.sqrt(2.0), rel=1e-9)
    assert out["rpe_lag1_m"] == pytest.approx(0.001, rel=1e-9)


def test_keyframe_jumps_measure_the_step_at_a_change() -> None:
    """A 5 mm step where the reference key changes, none elsewhere: the jump
    is the step; ids of -1 (unknown) never count as a change."""
    t = np.arange(40) / 30.0
    q = np.tile([0.0, 0.0, 0.0, 1.0], (40, 1))
    truth = Trajectory(t, np.stack([0.5 * t, 0 * t, 0 * t], axis=1), q)
    ids = np.repeat([0, 1, 2, 3], 10)
    offset = np.where(ids >= 1, 0.005, 0.0) + np.where(ids >= 3, 0.002, 0.0)
    est = Trajectory(t, truth.p_xyz_m + np.stack([0 * t, offset, 0 * t], axis=1), q)
    out = lag_metrics(est, truth, ids)
    assert out["keyframe_changes"] == 3
    assert out["keyframe_jump_max_m"] == pytest.approx(0.005, abs=1e-12)
    assert out["keyframe_jump_median_m"] == pytest.approx(0.002, abs=1e-12)
    np.testing.assert_array_equal(np.flatnonzero(out["key_change"]), [10, 20, 30])
    unknown = lag_metrics(est, truth, np.full(40, -1))
    assert unknown["keyframe_changes"] == 0 and np.isnan(unknown["keyframe_jump_max_m"])
    with pytest.raises(ValueError):
        lag_metrics(est, truth, ids[:-1])


def test_plot_marks_key_changes(tmp_path) -> None:
    from onboard.outputs.plot import plot_trajectory

    gt, est = _pair()
    ids = np.repeat(np.arange(4), N // 4)
    m = evaluate(est, gt, reference_keyframe_id=ids)
    assert m.keyframe_changes == 3 and m.key_change.sum() == 3
    path = tmp_path / "traj.png"
    assert plot_trajectory(path, m.estimate_aligned_xyz_m, gt.p_xyz_m, m.t_s, m.ate_errors_m,
                           "t", step_errors_m=m.step_errors_m, key_change=m.key_change)
    assert path.read_bytes().startswith(b"\x89PNG")
