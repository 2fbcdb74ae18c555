"""Evaluation metrics against evo's CLI, Umeyama sanity, PLY round trip, plot."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from onboard.core.evaluation import evaluate, ground_truth_at, rpe_pairs_by_time, umeyama_se3
from onboard.core.trajectory import Trajectory, read_tum, write_tum
from onboard.outputs.plot import plot_trajectory
from onboard.outputs.ply import read_ply, write_ply

RATE_HZ = 30.0
N_POSES = 300


def _synthetic_pair(seed: int = 0) -> tuple[Trajectory, Trajectory]:
    """Ground truth (a rising, yawing, pitching loop) and an estimate in another
    world frame with noise and slow drift, both at 30 Hz."""
    rng = np.random.default_rng(seed)
    t_s = 1000.0 + np.arange(N_POSES) / RATE_HZ
    phase = (t_s - t_s[0]) / 3.0
    p_gt = np.stack([2.0 * np.cos(phase), 1.5 * np.sin(phase), 0.2 * phase], axis=1)
    euler_zyx = np.stack([phase, 0.3 * np.sin(2 * phase), 0.1 * phase], axis=1)
    rot_gt = Rotation.from_euler("zyx", euler_zyx)
    gt = Trajectory(t_s, p_gt, rot_gt.as_quat())

    r_world = Rotation.from_euler("zyx", [0.7, -0.2, 0.4])
    t_world = np.array([3.0, -1.0, 0.5])
    drift = np.cumsum(rng.normal(0.0, 0.002, size=(N_POSES, 3)), axis=0)
    p_est = r_world.apply(p_gt + drift + rng.normal(0.0, 0.01, size=(N_POSES, 3))) + t_world
    rot_est = r_world * rot_gt * Rotation.from_rotvec(rng.normal(0.0, 0.01, size=(N_POSES, 3)))
    est = Trajectory(t_s, p_est, rot_est.as_quat())
    return gt, est


@pytest.fixture()
def tum_files(tmp_path: Path) -> tuple[Path, Path, Trajectory, Trajectory]:
    gt, est = _synthetic_pair()
    gt_path, est_path = tmp_path / "gt.txt", tmp_path / "est.txt"
    write_tum(gt_path, gt.t_s, gt.p_xyz_m, gt.q_xyzw)
    write_tum(est_path, est.t_s, est.p_xyz_m, est.q_xyzw)
    # Evaluate what evo reads (6-decimal text), not the in-memory originals.
    return gt_path, est_path, read_tum(gt_path), read_tum(est_path)


def test_umeyama_recovers_known_transform() -> None:
    rng = np.random.default_rng(1)
    src = rng.normal(size=(50, 3))
    r_true = Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix()
    t_true = np.array([1.0, -2.0, 0.5])
    r, t = umeyama_se3(src, src @ r_true.T + t_true)
    np.testing.assert_allclose(r, r_true, atol=1e-12)
    np.testing.assert_allclose(t, t_true, atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_umeyama_never_returns_reflection() -> None:
    rng = np.random.default_rng(2)
    src = rng.normal(size=(40, 3))
    dst = src * np.array([1.0, 1.0, -1.0])  # mirror image: best orthogonal fit is a reflection
    r, _ = umeyama_se3(src, dst)
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_ate_zero_for_rigidly_moved_copy() -> None:
    gt, _ = _synthetic_pair()
    r_world = Rotation.from_euler("xyz", [0.5, 1.0, -2.0])
    moved = Trajectory(
        gt.t_s,
        r_world.apply(gt.p_xyz_m) + [4.0, 5.0, 6.0],
        (r_world * Rotation.from_quat(gt.q_xyzw)).as_quat(),
    )
    m = evaluate(moved, gt)
    assert m.frames_evaluated == N_POSES
    assert m.ate_rmse_m < 1e-9
    assert m.rpe_trans_rmse_m < 1e-9
    assert m.rpe_rot_rmse_deg < 1e-5
    np.testing.assert_allclose(m.estimate_aligned_xyz_m, gt.p_xyz_m, atol=1e-9)
    d = m.as_dict()
    json.dumps(d, allow_nan=False)
    assert "ate_errors_m" not in d and d["frames_evaluated"] == N_POSES


def test_ate_matches_evo(tum_files, evo) -> None:
    gt_path, est_path, gt, est = tum_files
    stats, evo_errors = evo("evo_ape", ["tum", str(gt_path), str(est_path), "-a"])
    m = evaluate(est, gt)
    assert m.ate_rmse_m > 0.01  # the test would be vacuous on a perfect estimate
    assert m.ate_rmse_m == pytest.approx(stats["rmse"], abs=1e-6)
    assert m.ate_mean_m == pytest.approx(stats["mean"], abs=1e-6)
    assert m.ate_median_m == pytest.approx(stats["median"], abs=1e-6)
    assert m.ate_max_m == pytest.approx(stats["max"], abs=1e-6)
    np.testing.assert_allclose(m.ate_errors_m, evo_errors, atol=1e-6)


@pytest.mark.parametrize("all_pairs", [True, False])
def test_rpe_matches_evo(tum_files, evo, all_pairs: bool) -> None:
    """evo has no time-based delta; at a uniform 30 Hz, 1 s == 30 frames."""
    gt_path, est_path, gt, est = tum_files
    base = ["tum", str(gt_path), str(est_path), "--delta", "30", "--delta_unit", "f"]
    base += ["--all_pairs"] if all_pairs else []
    trans, trans_err = evo("evo_rpe", base + ["-r", "trans_part"])
    rot, rot_err = evo("evo_rpe", base + ["-r", "angle_deg"])
    m = evaluate(est, gt, rpe_delta_s=1.0, rpe_all_pairs=all_pairs)
    assert m.rpe_pairs == len(trans_err) == (N_POSES - 30 if all_pairs else (N_POSES - 1) // 30)
    assert m.rpe_trans_rmse_m == pytest.approx(trans["rmse"], abs=1e-6)
    assert m.rpe_rot_rmse_deg == pytest.approx(rot["rmse"], abs=1e-6)
    np.testing.assert_allclose(m.rpe_trans_errors_m, trans_err, atol=1e-6)
    np.testing.assert_allclose(m.rpe_rot_errors_deg, rot_err, atol=1e-6)


def test_rpe_pairs_by_time_rules() -> None:
    t = np.array([0.0, 0.4, 0.999999, 1.5, 2.1, 6.0, 6.5, 7.0])
    # 0.999999 counts as 1 s (rounded TUM times); pairs into 6.0 span a gap.
    np.testing.assert_array_equal(
        rpe_pairs_by_time(t, 1.0, all_pairs=True), [[0, 2], [1, 3], [2, 4], [5, 7]]
    )
    np.testing.assert_array_equal(
        rpe_pairs_by_time(t, 1.0, all_pairs=False), [[0, 2], [2, 4], [5, 7]]
    )
    assert rpe_pairs_by_time(t[:2], 1.0).shape == (0, 2)


def test_ground_truth_at_masks_outside_and_gaps() -> None:
    gt = Trajectory(
        np.array([0.0, 1.0, 2.0, 5.0]),
        np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [5, 0, 0]]),
        np.tile([0.0, 0, 0, 1], (4, 1)),
    )
    # 3.0 lies in the 3 s gap; 5.0 is the last sample itself (valid whatever
    # gap precedes it); 6.0 would be extrapolation.
    sampled, valid = ground_truth_at(np.array([-0.5, 0.5, 1.5, 3.0, 5.0, 6.0]), gt, max_gap_s=1.5)
    np.testing.assert_array_equal(valid, [False, True, True, False, True, False])
    np.testing.assert_allclose(sampled.p_xyz_m[:, 0], [0.5, 1.5, 5.0])
    np.testing.assert_allclose(sampled.t_s, [0.5, 1.5, 5.0])


def test_evaluate_rejects_mismatched_times() -> None:
    gt, est = _synthetic_pair()
    shifted = Trajectory(est.t_s + 0.01, est.p_xyz_m, est.q_xyzw)
    with pytest.raises(ValueError):
        evaluate(shifted, gt)


def test_ply_round_trip_bit_exact(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(100_000, 3)).astype(np.float32)
    xyz[0] = [np.inf, -0.0, np.float32(1e-40)]  # odd values must survive too
    rgb = rng.integers(0, 256, size=(100_000, 3), dtype=np.uint8)
    path = tmp_path / "map.ply"
    write_ply(path, xyz, rgb)
    xyz2, rgb2 = read_ply(path)
    assert xyz2.dtype == np.float32 and rgb2.dtype == np.uint8
    assert xyz2.tobytes() == xyz.tobytes()
    assert rgb2.tobytes() == rgb.tobytes()
    header_len = path.read_bytes().index(b"end_header\n") + len(b"end_header\n")
    assert path.stat().st_size == header_len + 100_000 * 15
    assert [p.name for p in tmp_path.iterdir()] == ["map.ply"]  # no temp files left


def test_ply_empty_and_bad_input(tmp_path: Path) -> None:
    path = tmp_path / "empty.ply"
    write_ply(path, np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8))
    xyz, rgb = read_ply(path)
    assert xyz.shape == (0, 3) and rgb.shape == (0, 3)
    with pytest.raises(ValueError):
        write_ply(path, np.zeros((2, 3)), np.zeros((2, 3)))  # float colours


def test_ply_truncated_raises(tmp_path: Path) -> None:
    path = tmp_path / "cut.ply"
    write_ply(path, np.ones((10, 3), np.float32), np.ones((10, 3), np.uint8))
    path.write_bytes(path.read_bytes()[:-5])
    with pytest.raises(ValueError):
        read_ply(path)


def test_plot_writes_png(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    gt, est = _synthetic_pair()
    m = evaluate(est, gt)
    path = tmp_path / "traj.png"
    assert plot_trajectory(
        path, m.estimate_aligned_xyz_m, gt.p_xyz_m, m.t_s, m.ate_errors_m, "synthetic"
    )
    data = path.read_bytes()
    assert data.startswith(b"\x89PNG") and len(data) > 10_000
