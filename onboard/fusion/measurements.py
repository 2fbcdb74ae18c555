"""Each tracker's motion as a measurement for the fused filter: the position
covariance it carries, from the tracker's own quality signals.

NI-SLAM measures the shift of the correlation peak across the image (the
key's x, y) and the depth step along its optical axis (z, Eq. 18) separately,
so its covariance is built in the key's axes and rotated into W (the frame's
attitude stands in for the key's, which it is within a key's span):
  - x, y: the sub-cell peak's accuracy, `nislam_peak_cells` cells of the
    key's resolution at a firm peak, growing as psr_full / PSR below
    `psr_full` (a flat or ambiguous response: a corridor seen along its axis,
    whose walls collapse in the axonometric view, gives a low PSR);
  - z: the scatter of the well-matched depth differences over the square root
    of the number of independent samples among them (`nislam_cells_per_sample`
    neighbouring cells share their error: the sensor's noise is smooth), so
    few well-matched cells give a loose depth step.
The tracker's own `pose_var` is the authors' (ref. §10): the response's
whole width and the raw depth scatter, the spread of one cell's measurement
rather than the accuracy of the frame's, 5-20x the error it makes.

FastORB (`pose_var` from the PnP Hessian, onboard.fastorb.pose): sigma^2 H^-1
with sigma^2 the robust residual variance: more inliers, spread wider over the
image and in depth, give a better-conditioned H. Below `fastorb_full_inliers`
inliers it grows as (fastorb_full_inliers / inliers)^2: with few points a
wrong one moves the pose more than the Hessian says.

NI-SLAM's x and y also carry the attitude's own error, `attitude_var_m2`:
the AHRS's white noise times the matched cells' depth (onboard.nislam.attitude_var),
half from the frame's attitude (white, here) and half from the key's (the
same for all frames on that key: it widens the key's clone, key_attitude_cov).

Both are then scaled by `*_var_scale` and floored at `min_sd_m` per axis.
"""

from __future__ import annotations

import math

import numpy as np

from onboard.core.messages import TrackResult
from onboard.fusion.params import FusionParams


def nislam_cov(r: TrackResult, p: FusionParams) -> np.ndarray:
    """3x3 position covariance (W) of an NI-SLAM result."""
    R = np.asarray(r.R_W_C, dtype=np.float64)
    firm = 1.0
    if math.isfinite(r.psr) and r.psr > 0.0:
        firm = max(1.0, p.psr_full / r.psr)
    sd_xy = p.nislam_peak_cells * r.res_m * firm
    var_z = _key_depth_scatter(r.pose_var[:3], R)
    samples = max(r.matched_cells / p.nislam_cells_per_sample, 1.0)
    var_key = np.array([sd_xy**2, sd_xy**2, var_z / samples]) * p.nislam_var_scale
    # The AHRS's attitude noise moves the peak by depth x error (onboard.nislam.attitude_var):
    # the frame's half here, white; the key's half is shared by every frame on
    # that key, so it widens the key's clone instead (key_attitude_cov).
    var_key[:2] += 0.5 * r.attitude_var_m2
    var_key = np.maximum(var_key, p.min_sd_m**2)
    return R @ np.diag(var_key) @ R.T


def key_attitude_cov(r: TrackResult) -> np.ndarray:
    """3x3 (W): the key's share of NI-SLAM's attitude term, the same error in
    every frame matched against that key (its attitude is looked up once per
    key time), so a bias of the key's clone rather than white noise: treated
    as white the filter would average it away over the key's frames."""
    R = np.asarray(r.R_W_C, dtype=np.float64)
    a = 0.5 * r.attitude_var_m2 if math.isfinite(r.attitude_var_m2) else 0.0
    return R @ np.diag([a, a, 0.0]) @ R.T


def _key_depth_scatter(var_W: np.ndarray, R: np.ndarray) -> float:
    """The depth scatter NI-SLAM put on its key's z axis, from the world
    diagonal it reports (diag(R diag(a, a, b) R^T): d_j = a (1 - R_j2^2) + b R_j2^2)."""
    w = R[:, 2] ** 2
    X = np.stack([1.0 - w, w], axis=1)
    ab, *_ = np.linalg.lstsq(X, np.asarray(var_W, dtype=np.float64), rcond=None)
    return float(max(ab[1], 0.0))


def fastorb_cov(r: TrackResult, p: FusionParams) -> np.ndarray:
    """3x3 position covariance (W) of a FastORB result (matched_cells: its inliers)."""
    var = np.asarray(r.pose_var[:3], dtype=np.float64) * p.fastorb_var_scale
    few = max(1.0, p.fastorb_full_inliers / max(r.matched_cells, 1))
    return _floored(var * few**2, p.min_sd_m)


def _floored(var: np.ndarray, min_sd_m: float) -> np.ndarray:
    var = np.where(np.isfinite(var), var, np.inf)
    return np.diag(np.maximum(var, min_sd_m**2))


COVARIANCE_MODELS = {"nislam": nislam_cov, "fastorb": fastorb_cov}
