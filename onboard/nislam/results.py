"""What NI-SLAM reports for a frame: the `TrackResult` of a restart or of a
frame without a trusted pose, the quality from the PSR, and the position
variance of a match (ref. §10). Pure functions; the tracker decides."""

from __future__ import annotations

import math

import numpy as np

from onboard.core.messages import KeyframeCloud, TrackResult, TrackState
from onboard.nislam.correlation import Peak
from onboard.nislam.keys import Key

# The authors' fixed attitude variance (rad^2, ref. §10).
ATTITUDE_VAR_RAD2 = 2.0 * 4.592449e-6
# A restart places the key where the last trusted pose was: 1 cm, 0.6 deg.
RESTART_VAR = np.full(6, 1e-4)


def quality_from_psr(psr: float, psr_lost: float, psr_refine: float) -> int:
    """0-100 between the PSR at which a match is lost and the one at which
    the key is refined (Eq. 19's gate): MAVLink's quality field."""
    span = max(psr_refine - psr_lost, 1e-6)
    return int(np.clip(round(100.0 * (psr - psr_lost) / span), 1, 100))


def pose_variance(peak: Peak, res_m: float, var_z_m2: float, r_W_key: np.ndarray) -> np.ndarray:
    """Position variances in the world frame, attitude variances (ref. §10).

    In key axes: lateral from the response treated as an isotropic 2-D
    Gaussian (s^2 * volume / (2 pi peak)), floored at a tenth of a cell;
    depth from the scatter of the matched depth differences, floored at
    5 mm. The diagonal is carried into the world frame (diag of R S R^T).
    """
    vol = max(peak.response_sum, 0.0)
    var_xy = res_m**2 * max(vol / (2.0 * math.pi * max(peak.value, 1e-9)), 0.01)
    var_key = np.array([var_xy, var_xy, max(var_z_m2, 0.005**2)])
    rot = ATTITUDE_VAR_RAD2
    return np.concatenate([(r_W_key * r_W_key) @ var_key, [rot, rot, rot]])


def restart_result(
    t_s: float, p_W_m: np.ndarray, R_W_C: np.ndarray, key: Key, reset_counter: int,
    attitude_offset_s: float, finished: tuple[KeyframeCloud, ...],
) -> TrackResult:
    """The first frame of a new key after a start or a lost spell: posed
    where the last trusted pose was (the reset counter marks the jump)."""
    return TrackResult(
        t_s=t_s,
        state=TrackState.TRACKING,
        trusted=True,
        p_W_m=p_W_m,
        R_W_C=R_W_C,
        pose_var=RESTART_VAR.copy(),
        quality=50,
        psr=float("nan"),
        keyframe_id=key.keyframe_id,
        new_keyframe=True,
        reset_counter=reset_counter,
        lost_reason=None,
        shift_cells=(0.0, 0.0),
        tz_m=0.0,
        res_m=key.img.res_m,
        rotation_residual_rad=np.zeros(3),
        attitude_offset_s=attitude_offset_s,
        matched_cells=0,
        finished_keyframes=finished,
        reference_keyframe_id=key.keyframe_id,
        reference_offset_m=np.zeros(3),
    )


def lost_result(
    t_s: float, reason: str, key: Key | None, reset_counter: int, attitude_offset_s: float,
    finished: tuple[KeyframeCloud, ...] = (),
) -> TrackResult:
    """A frame without a trusted pose (`reason` says why)."""
    return TrackResult(
        t_s=t_s,
        state=TrackState.LOST if key is not None else TrackState.INITIALIZING,
        trusted=False,
        p_W_m=None,
        R_W_C=None,
        pose_var=np.full(6, np.nan),
        quality=0,
        psr=float("nan"),
        keyframe_id=-1 if key is None else key.keyframe_id,
        new_keyframe=False,
        reset_counter=reset_counter,
        lost_reason=reason,
        shift_cells=(0.0, 0.0),
        tz_m=0.0,
        res_m=0.0 if key is None else key.img.res_m,
        rotation_residual_rad=np.zeros(3),
        attitude_offset_s=attitude_offset_s,
        matched_cells=0,
        finished_keyframes=finished,
    )
