"""Trajectory accuracy against ground truth: ATE after SE(3) alignment, RPE over
a time delta and over 1/3/10/30 frames, path length ratio, and the error jump at
key-frame changes.

Numbers are meant to be identical to `evo` (checked in tests/test_evaluation.py):
- ATE == `evo_ape tum GT EST -a` (translation part, Umeyama without scale).
- RPE with all pairs == `evo_rpe tum GT EST --delta K --delta_unit f --all_pairs`
  and with consecutive pairs == the same without `--all_pairs`, when the data are
  uniformly sampled so that K frames span `rpe_delta_s`. evo has no time-based
  delta unit (its `--delta_unit` accepts only f/d/r/m), so the time pairing here
  is our own rule, chosen to reduce to evo's frame pairing on uniform data.
- `rpe_lagK_m` == `evo_rpe tum GT EST --delta K --delta_unit f --pose_relation
  trans_part --all_pairs` (RMSE) over the evaluated rows, whatever their
  spacing in time; `rpe_rot_lag1_deg` the same with `angle_deg` and K = 1.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from onboard.core.trajectory import Trajectory

log = logging.getLogger(__name__)

# TUM files store times with 6 decimals, so a nominal 1.000 s difference can read
# as 0.999999 s; without this slack the pairing would skip to the next frame.
_PAIR_TIME_TOL_S = 1e-5

# A pair spanning much more than delta straddles a hole in the data (tracking lost
# or no ground truth); its drift would be reported as "per delta", so drop it.
_RPE_MAX_SPAN_FACTOR = 1.5

# Frame lags of the short-range RPE: 1 frame is the jitter the flight
# controller's velocity estimate sees, 30 (1 s at 30 Hz) the drift.
RPE_LAGS_FRAMES = (1, 3, 10, 30)


def umeyama_se3(src_xyz: np.ndarray, dst_xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid (R, t) minimising sum ||dst - (R src + t)||^2, no scale.

    Umeyama 1991 (eqs. 34-43), the S = diag(1, 1, -1) fix keeping R a proper
    rotation when the best orthogonal fit would be a reflection. Same result as
    `evo.core.geometry.umeyama_alignment(src.T, dst.T, with_scale=False)`.
    Degenerate inputs (collinear or coincident points) are not an error: any
    minimiser returned maps the points identically, so the residual is still
    well defined; evo raises instead.
    """
    src = np.asarray(src_xyz, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(dst_xyz, dtype=np.float64).reshape(-1, 3)
    if src.shape != dst.shape:
        raise ValueError(f"point sets differ in shape: {src.shape} vs {dst.shape}")
    if len(src) == 0:
        raise ValueError("cannot align empty point sets")
    mean_src = src.mean(axis=0)
    mean_dst = dst.mean(axis=0)
    cov = (dst - mean_dst).T @ (src - mean_src) / len(src)
    u, d, vt = np.linalg.svd(cov)
    if np.count_nonzero(d > np.finfo(np.float64).eps) < 2:
        log.debug("degenerate covariance in Umeyama alignment (rank < 2)")
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        s[2, 2] = -1.0
    r = u @ s @ vt
    t = mean_dst - r @ mean_src
    return r, t


@dataclass
class TrajectoryMetrics:
    """Accuracy of an estimate against ground truth at the same timestamps.

    Scalars go to `as_dict()`; the arrays are for plots and further analysis.
    RPE fields are NaN when no pair spans `rpe_delta_s`.
    """

    frames_evaluated: int
    ate_rmse_m: float
    ate_mean_m: float
    ate_median_m: float
    ate_max_m: float
    rpe_trans_rmse_m: float
    rpe_rot_rmse_deg: float
    rpe_delta_s: float
    rpe_pairs: int
    t_s: np.ndarray = field(repr=False)
    # Estimate positions mapped into the ground-truth frame: p_gt = R p_est + t.
    estimate_aligned_xyz_m: np.ndarray = field(repr=False)
    ate_errors_m: np.ndarray = field(repr=False)
    R_gt_est: np.ndarray = field(repr=False)
    t_gt_est_m: np.ndarray = field(repr=False)
    rpe_trans_errors_m: np.ndarray = field(repr=False)
    rpe_rot_errors_deg: np.ndarray = field(repr=False)
    # Frame-lag RPE (see lag_metrics); NaN when the trajectory is shorter.
    rpe_lag1_m: float = float("nan")
    rpe_lag3_m: float = float("nan")
    rpe_lag10_m: float = float("nan")
    rpe_lag30_m: float = float("nan")
    rpe_rot_lag1_deg: float = float("nan")
    path_length_ratio: float = float("nan")
    keyframe_changes: int = 0
    keyframe_jump_median_m: float = float("nan")
    keyframe_jump_max_m: float = float("nan")
    # Per row i >= 1: translation error of the motion from row i-1 to row i
    # (the lag-1 RPE, NaN at row 0), and whether row i changed key.
    step_errors_m: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    key_change: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0, dtype=bool))

    def as_dict(self) -> dict[str, float | int | None]:
        """Scalar metrics only, JSON-able (non-finite values become None)."""
        out: dict[str, float | int | None] = {}
        for name, value in vars(self).items():
            if isinstance(value, np.ndarray):
                continue
            if isinstance(value, (int, np.integer)):
                out[name] = int(value)
            else:
                v = float(value)
                out[name] = v if np.isfinite(v) else None
        return out


def ground_truth_at(
    estimate_t_s: np.ndarray, groundtruth: Trajectory, max_gap_s: float
) -> tuple[Trajectory, np.ndarray]:
    """Ground truth interpolated at the estimate's times.

    Returns (trajectory of the valid rows only, valid mask over `estimate_t_s`);
    times outside the ground truth or inside gaps longer than `max_gap_s` are
    invalid, so apply the mask to the estimate before `evaluate`.
    """
    t = np.asarray(estimate_t_s, dtype=np.float64)
    p, q, valid = groundtruth.interpolate(t, max_gap_s)
    return Trajectory(t[valid], p[valid], q[valid]), valid


def rpe_pairs_by_time(t_s: np.ndarray, delta_s: float, all_pairs: bool = True) -> np.ndarray:
    """Index pairs (i, j) for RPE, (K, 2) int.

    j is the first index with t_j - t_i >= delta_s (minus a small tolerance for
    rounded timestamps). With `all_pairs` every i starts a pair (as evo's
    `--all_pairs`); otherwise pairs are chained, the next starting at the
    previous j (as evo's default). Pairs spanning more than
    `_RPE_MAX_SPAN_FACTOR * delta_s` are dropped.
    """
    t = np.asarray(t_s, dtype=np.float64)
    if delta_s <= 0:
        raise ValueError("delta_s must be positive")
    if all_pairs:
        i = np.arange(len(t))
        j = np.searchsorted(t, t + delta_s - _PAIR_TIME_TOL_S, side="left")
        ok = j < len(t)
        pairs = np.stack([i[ok], j[ok]], axis=1)
    else:
        chained: list[tuple[int, int]] = []
        i = 0
        while i < len(t):
            j = int(np.searchsorted(t, t[i] + delta_s - _PAIR_TIME_TOL_S, side="left"))
            if j >= len(t):
                break
            chained.append((i, j))
            i = j
        pairs = np.asarray(chained, dtype=np.int64).reshape(-1, 2)
    if len(pairs) == 0:
        return pairs.astype(np.int64)
    span_s = t[pairs[:, 1]] - t[pairs[:, 0]]
    keep = span_s <= _RPE_MAX_SPAN_FACTOR * delta_s
    if not keep.all():
        log.info(
            "RPE: dropped %d of %d pairs spanning a data gap (> %.2f s)",
            int((~keep).sum()), len(pairs), _RPE_MAX_SPAN_FACTOR * delta_s,
        )
    return pairs[keep].astype(np.int64)


def relative_pose_errors(
    estimate: Trajectory, groundtruth: Trajectory, pairs: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per pair: translation norm [m] and rotation angle [deg] of
    E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j), Q ground truth, P estimate (TUM RGB-D /
    evo definition). Invariant to a global rigid transform of either trajectory,
    so no alignment is needed."""
    if len(pairs) == 0:
        return np.zeros(0), np.zeros(0)
    i, j = pairs[:, 0], pairs[:, 1]
    rq = Rotation.from_quat(groundtruth.q_xyzw)
    rp = Rotation.from_quat(estimate.q_xyzw)
    # Relative motion i -> j expressed in frame i.
    rq_rel = rq[i].inv() * rq[j]
    rp_rel = rp[i].inv() * rp[j]
    tq_rel = rq[i].inv().apply(groundtruth.p_xyz_m[j] - groundtruth.p_xyz_m[i])
    tp_rel = rp[i].inv().apply(estimate.p_xyz_m[j] - estimate.p_xyz_m[i])
    trans_err_m = np.linalg.norm(rq_rel.inv().apply(tp_rel - tq_rel), axis=1)
    rot_err_deg = np.degrees((rq_rel.inv() * rp_rel).magnitude())
    return trans_err_m, rot_err_deg


def rmse(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def rpe_pairs_by_frames(n: int, lag: int, all_pairs: bool = True) -> np.ndarray:
    """Index pairs (i, i + lag), (K, 2) int: every i with `all_pairs`, else
    i = 0, lag, 2 lag, ... (evo's `filter_pairs_by_index`)."""
    if lag < 1:
        raise ValueError("lag must be >= 1 frame")
    starts = np.arange(n - lag) if all_pairs else np.arange(0, n - lag, lag)
    return np.stack([starts, starts + lag], axis=1).astype(np.int64)


def path_length_m(p_xyz_m: np.ndarray) -> float:
    p = np.asarray(p_xyz_m, dtype=np.float64).reshape(-1, 3)
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def lag_metrics(
    estimate: Trajectory,
    groundtruth_at_estimate: Trajectory,
    reference_keyframe_id: np.ndarray | None = None,
) -> dict[str, object]:
    """Short-range accuracy of rows that share stamps (no alignment needed).

    - `rpe_lagK_m`: RMSE of the translation error of the relative motion over
      K rows (all pairs), K in RPE_LAGS_FRAMES; `rpe_rot_lag1_deg` the rotation.
    - `path_length_ratio`: length of the estimated path over the true one,
      summed over consecutive rows; frame-to-frame jitter inflates it.
    - key-frame jumps: where `reference_keyframe_id` (the key each row's pose
      was measured against; -1 = unknown) changes between consecutive rows,
      the lag-1 error across the change (`keyframe_jump_median_m`, `_max_m`).
    """
    n = len(estimate)
    out: dict[str, object] = {}
    step = np.full(n, np.nan)
    for lag in RPE_LAGS_FRAMES:
        trans_m, rot_deg = relative_pose_errors(
            estimate, groundtruth_at_estimate, rpe_pairs_by_frames(n, lag)
        )
        out[f"rpe_lag{lag}_m"] = rmse(trans_m)
        if lag == 1:
            out["rpe_rot_lag1_deg"] = rmse(rot_deg)
            step[1:] = trans_m
    true_len_m = path_length_m(groundtruth_at_estimate.p_xyz_m)
    out["path_length_ratio"] = (
        path_length_m(estimate.p_xyz_m) / true_len_m if true_len_m > 0 else float("nan")
    )
    change = np.zeros(n, dtype=bool)
    if reference_keyframe_id is not None:
        ids = np.asarray(reference_keyframe_id, dtype=np.int64)
        if len(ids) != n:
            raise ValueError(f"reference_keyframe_id has {len(ids)} rows, estimate {n}")
        change[1:] = (ids[1:] != ids[:-1]) & (ids[1:] >= 0) & (ids[:-1] >= 0)
    jumps = step[change]
    out["keyframe_changes"] = int(change.sum())
    out["keyframe_jump_median_m"] = float(np.median(jumps)) if len(jumps) else float("nan")
    out["keyframe_jump_max_m"] = float(np.max(jumps)) if len(jumps) else float("nan")
    out["step_errors_m"] = step
    out["key_change"] = change
    return out


def evaluate(
    estimate: Trajectory,
    groundtruth_at_estimate: Trajectory,
    rpe_delta_s: float = 1.0,
    rpe_all_pairs: bool = True,
    reference_keyframe_id: np.ndarray | None = None,
) -> TrajectoryMetrics:
    """ATE (after SE(3) Umeyama alignment over all frames), RPE over
    `rpe_delta_s` and the frame-lag metrics of `lag_metrics`.

    Both trajectories must share timestamps row for row (see `ground_truth_at`);
    `reference_keyframe_id`, when given, too.
    """
    n = len(estimate)
    if n != len(groundtruth_at_estimate):
        raise ValueError(
            f"length mismatch: estimate {n}, ground truth {len(groundtruth_at_estimate)}"
        )
    if n == 0:
        raise ValueError("no frames to evaluate")
    if not np.allclose(estimate.t_s, groundtruth_at_estimate.t_s, rtol=0.0, atol=1e-6):
        raise ValueError(
            "estimate and ground truth timestamps differ; interpolate the ground truth first"
        )

    r, t = umeyama_se3(estimate.p_xyz_m, groundtruth_at_estimate.p_xyz_m)
    aligned_xyz_m = estimate.p_xyz_m @ r.T + t
    ate_m = np.linalg.norm(aligned_xyz_m - groundtruth_at_estimate.p_xyz_m, axis=1)

    pairs = rpe_pairs_by_time(estimate.t_s, rpe_delta_s, all_pairs=rpe_all_pairs)
    rpe_trans_m, rpe_rot_deg = relative_pose_errors(estimate, groundtruth_at_estimate, pairs)
    if len(pairs) == 0:
        log.info("RPE: no pair spans %.3f s in %d frames", rpe_delta_s, n)

    return TrajectoryMetrics(
        frames_evaluated=n,
        ate_rmse_m=rmse(ate_m),
        ate_mean_m=float(np.mean(ate_m)),
        ate_median_m=float(np.median(ate_m)),
        ate_max_m=float(np.max(ate_m)),
        rpe_trans_rmse_m=rmse(rpe_trans_m),
        rpe_rot_rmse_deg=rmse(rpe_rot_deg),
        rpe_delta_s=float(rpe_delta_s),
        rpe_pairs=len(pairs),
        t_s=np.asarray(estimate.t_s, dtype=np.float64),
        estimate_aligned_xyz_m=aligned_xyz_m,
        ate_errors_m=ate_m,
        R_gt_est=r,
        t_gt_est_m=t,
        rpe_trans_errors_m=rpe_trans_m,
        rpe_rot_errors_deg=rpe_rot_deg,
        **lag_metrics(estimate, groundtruth_at_estimate, reference_keyframe_id),  # type: ignore[arg-type]
    )


