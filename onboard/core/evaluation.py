"""Trajectory accuracy against ground truth: ATE after SE(3) alignment, RPE over
a time delta, and a diagnostic plot.

Numbers are meant to be identical to `evo` (checked in tests/test_evaluation.py):
- ATE == `evo_ape tum GT EST -a` (translation part, Umeyama without scale).
- RPE with all pairs == `evo_rpe tum GT EST --delta K --delta_unit f --all_pairs`
  and with consecutive pairs == the same without `--all_pairs`, when the data are
  uniformly sampled so that K frames span `rpe_delta_s`. evo has no time-based
  delta unit (its `--delta_unit` accepts only f/d/r/m), so the time pairing here
  is our own rule, chosen to reduce to evo's frame pairing on uniform data.
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


def evaluate(
    estimate: Trajectory,
    groundtruth_at_estimate: Trajectory,
    rpe_delta_s: float = 1.0,
    rpe_all_pairs: bool = True,
) -> TrajectoryMetrics:
    """ATE (after SE(3) Umeyama alignment over all frames) and RPE over `rpe_delta_s`.

    Both trajectories must share timestamps row for row (see `ground_truth_at`).
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
    )


