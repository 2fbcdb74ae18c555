"""The attitude's own error in NI-SLAM's translation covariance.

NI-SLAM takes the rotation from the AHRS and measures only translation: the
current cloud is rotated by R_rel = R_key^T R_cur (ref. §2) and projected
along the key's optical axis. An attitude error delta (rad, small) rotates a
point P of the cloud by delta x P, so a cell at depth z moves across the image
by z * delta (x: delta_y z, y: -delta_x z) and the correlation peak, the
texture-weighted mean of those moves, by the matched cells' mean depth times
delta. Along the optical axis the move is delta_x y - delta_y x: zero to first
order for cells around the axis, so the depth step (Eq. 18) is left alone.
R_rel carries the key's and the frame's attitude errors, independent white
noise of the same sd: twice the variance. docs/nislam-error-budget.md: 0.1 deg
of white attitude noise alone gives 8.5-9.8 mm of per-frame error, about
sqrt(2 axes x 2 attitudes) x 2.5 m x 1.75 mrad.
"""

from __future__ import annotations

import math

import numpy as np


def attitude_lateral_var_m2(mean_depth_m: float, attitude_sd_deg: float) -> float:
    """Variance [m^2] the attitude's white noise adds to each lateral axis of
    the key's view (x and y; the optical axis gets none, see module doc)."""
    if not (math.isfinite(mean_depth_m) and mean_depth_m > 0.0) or attitude_sd_deg <= 0.0:
        return 0.0
    sd_m = mean_depth_m * math.radians(attitude_sd_deg)  # lateral move of the peak per attitude
    return 2.0 * sd_m * sd_m  # key's and frame's attitude: independent


def with_attitude_var(pose_var: np.ndarray, r_W_key: np.ndarray, lateral_var_m2: float) -> np.ndarray:
    """NI-SLAM's (6,) world variances with `lateral_var_m2` added on the key's
    x and y axes, carried into W like the rest (diag of R S R^T). Only the
    reported pose_var: the key map keeps weighing offsets by the match's own."""
    add_W = (r_W_key * r_W_key) @ np.array([lateral_var_m2, lateral_var_m2, 0.0])
    return np.concatenate([pose_var[:3] + add_W, pose_var[3:]])
