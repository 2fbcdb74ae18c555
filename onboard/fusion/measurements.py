"""Each tracker's motion as a measurement for the fused filter: the position
covariance it carries, from the tracker's own quality signals.

NI-SLAM (`pose_var` from onboard.nislam.tracker._pose_variance): lateral from
the correlation response taken as a 2-D Gaussian (s^2 volume / (2 pi peak),
the sharper and higher the peak the smaller), along the key's axis from the
scatter of the well-matched depth differences (Eq. 18), rotated into W. A
weak peak (PSR towards psr_lost) is a less certain shift than the response
shape alone says, so the variance grows as (psr_full / PSR)^2 below psr_full.
The key axes the response cannot constrain (a corridor seen along its axis:
walls parallel to the optical axis collapse in the axonometric view) show as a
flat, wide response and so as a large lateral variance already.

FastORB (`pose_var` from the PnP Hessian, onboard.fastorb.pose): sigma^2 H^-1
with sigma^2 the robust residual variance: more inliers, and inliers spread
wider over the image and in depth, give a better-conditioned H.

Both are then scaled by a calibration factor (`[fusion] *_var_scale`) and
floored at `min_sd_m` per axis (docs/fusion.md has the figures).
"""

from __future__ import annotations

import math

import numpy as np

from onboard.core.messages import TrackResult
from onboard.fusion.params import FusionParams


def nislam_cov(r: TrackResult, p: FusionParams) -> np.ndarray:
    """3x3 position covariance (W) of an NI-SLAM result."""
    var = np.asarray(r.pose_var[:3], dtype=np.float64)
    scale = p.nislam_var_scale
    if math.isfinite(r.psr) and r.psr > 0.0:
        scale *= max(1.0, (p.psr_full / r.psr) ** 2)
    return _floored(var * scale, p.min_sd_m)


def fastorb_cov(r: TrackResult, p: FusionParams) -> np.ndarray:
    """3x3 position covariance (W) of a FastORB result."""
    var = np.asarray(r.pose_var[:3], dtype=np.float64)
    return _floored(var * p.fastorb_var_scale, p.min_sd_m)


def _floored(var: np.ndarray, min_sd_m: float) -> np.ndarray:
    var = np.where(np.isfinite(var), var, np.inf)
    return np.diag(np.maximum(var, min_sd_m**2))


COVARIANCE_MODELS = {"nislam": nislam_cov, "fastorb": fastorb_cov}
