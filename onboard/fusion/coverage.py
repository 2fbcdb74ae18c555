"""How honest a reported covariance is: the share of the true position error
that the reported 1-sigma covers.

The error is taken as the flight controller sees it: the pose stream starts
at its first pose, so the estimate and the ground truth are both measured
from their first sample, in the world axes (the AHRS world is the ground
truth's when the attitude comes from it, as in replays and synthetic flights).
For a consistent Gaussian estimate each axis' |error| <= sigma holds 68.3 %
of the time; far above means the covariance is too pessimistic (the flight
controller under-uses the pose), far below too optimistic (it over-trusts it).
"""

from __future__ import annotations

import numpy as np


def sigma1_coverage(p_est: np.ndarray, var_est: np.ndarray, p_true: np.ndarray) -> float | None:
    """Share of (sample, axis) pairs with |error| <= sigma; None without
    samples or finite variances. `p_est`, `p_true` (N, 3) at the same stamps,
    `var_est` (N, 3) the reported position variances."""
    p_est = np.asarray(p_est, dtype=np.float64).reshape(-1, 3)
    p_true = np.asarray(p_true, dtype=np.float64).reshape(-1, 3)
    var = np.asarray(var_est, dtype=np.float64).reshape(-1, 3)
    if len(p_est) == 0:
        return None
    err = (p_est - p_est[0]) - (p_true - p_true[0])
    ok = np.isfinite(var)
    if not ok.any():
        return None
    return float(np.mean(np.abs(err[ok]) <= np.sqrt(np.maximum(var[ok], 0.0))))
