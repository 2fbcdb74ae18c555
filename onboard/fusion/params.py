"""Fusion parameters (the `[fusion]` configuration section), read by
`onboard.fusion.fused.FusedTracker`.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class FusionParams:
    """Filter, gate and measurement-noise settings of the fused tracker
    (docs/fusion.md); the figures behind the defaults are in docs/results.md
    ("Fused tracker")."""

    # Motion model: constant velocity driven by white acceleration, its spectral
    # density's square root (m/s^2 per sqrt(Hz)): velocity sd grows by this * sqrt(dt).
    accel_sd_m_s2: float = 5.0
    initial_speed_sd_m_s: float = 0.5  # velocity is unknown at the first pose
    # Gate: a tracker's motion whose squared Mahalanobis distance to the
    # prediction (3 dof) exceeds this is left out (12: chi-square 99.3 %).
    gate_chi2: float = 12.0
    # The second tracker, against the state the first one updated: beyond this it is
    # an outlier (gone wild before it reports lost), left out (the same 99.3 %).
    outlier_chi2: float = 12.0
    # ... once the scale of the disagreement is known; while it is being learnt
    # the bound is k F(k, nu) (onboard.fusion.agreement), nu the dof seen plus
    # these for the trackers' own covariances (3: worth one frame's disagreement).
    outlier_prior_dof: float = 3.0
    key_clones: int = 24  # fused positions of a tracker's keys kept for it to come back to
    noise_adapt_gain: float = 0.02  # per frame both trackers measure: step of the covariance scale (fused._adapt)
    noise_scale_max: float = 100.0  # ... up to this many times their own figures
    # Measurement noise (onboard.fusion.measurements), scaled; the defaults put
    # the reported 1 sigma over 55-81 % of the error on the synthetic flights.
    nislam_var_scale: float = 1.0
    fastorb_var_scale: float = 4.0
    nislam_peak_cells: float = 0.3  # NI-SLAM lateral sd at a firm peak [cells of the key's resolution]
    psr_full: float = 60.0  # ... growing as psr_full / PSR below this PSR
    nislam_cells_per_sample: float = 64.0  # NI-SLAM depth: well-matched cells per independent sample
    fastorb_full_inliers: int = 150  # FastORB: below this many inliers the variance grows as (n_full / n)^2
    min_sd_m: float = 0.001  # floor of a measurement's position sd (per axis)
    axes_gain: float = 0.05  # per frame: a tracker's world axes in W follow the AHRS this fast (0: fixed at the anchor)
    # Output
    # Frozen copies of the last outputs, for the covariance of the displacement
    # the MAVLink velocity is differenced from (onboard.fusion.displacement):
    # they must reach back `[mavlink] velocity_window_s` (0.1 s: 3-4 frames at 30 Hz).
    velocity_clones: int = 6
    max_coast_s: float = 0.2  # no tracker for longer than this: lost (then reset_counter + 1)
    quality_sd_m: float = 0.002  # a motion measured this well (fused sd) has quality 100
