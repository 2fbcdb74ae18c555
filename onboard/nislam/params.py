"""NI-SLAM tracker parameters (the `[nislam]` configuration section).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class NislamParams:
    """Tracker parameters; defaults are the tuned values (see config/*.toml comments)."""

    grid_width: int = 480
    grid_height: int = 360
    adaptive_mu: float = 0.8  # share of points the key grid must hold (ref. §3; all launches: 0.8)
    max_distance_m: float = 4.0
    len_hist: int = 50
    hist_sample: int = 5
    min_depth_m: float = 0.2
    max_depth_m: float = 6.0
    pixel_stride: int = 2  # every 2nd pixel: ~1 point per cell at 1.5 m, a quarter of the work
    # ... but a key (and its frames) takes a finer step where its points would
    # land further apart than this many of its cells (sampling.stride_for_grid); 0 = never
    max_point_spacing_cells: float = 0.0
    # The pixel step of the key frame's cloud that Eq. 18's key images are
    # projected from (and the map's, which Eq. 19 refines). The key's filter
    # and layers keep its own step, what its frames look like, so the PSR, the
    # keys and the calibration do not change. At every 2nd pixel a far key
    # holds a point in one cell of two to four and Eq. 18 met the frame's
    # points in few cells (docs/nislam-error-budget.md, "A key's depth from
    # every pixel"). 0: the paper's Eq. 18, against the key's own step refined
    # by its frames (Eq. 19).
    key_depth_stride: int = 1
    kernel_sigma: float = 0.2
    lam: float = 0.1
    label_sigma_cells: float = 1.0
    # Sub-cell peak: centroid of the lobe above half height (false: a
    # parabola through 3 samples per axis, biased on a non-Gaussian lobe;
    # onboard/nislam/correlation.py, docs/nislam-error-budget.md)
    peak_lobe_centroid: bool = True
    psr_exclude_cells: int = 5  # sidelobe excludes an 11x11 window around the peak
    psr_keyframe: float = 30.0  # T_r of Eq. 17
    psr_refine: float = 100.0  # refine the key only on confident matches (ref. §8: 100)
    psr_lost: float = 6.0  # below this the match is not trusted
    min_valid_fraction: float = 0.05  # of grid cells covered by the current cloud
    gate_gray: float = 0.1  # |C~ - C_key| for a well-matched cell (Eq. 18, T_c)
    gate_depth_m: float = 0.1  # |Delta - median| for a well-matched cell
    min_matched_cells: int = 200
    search_radius_m: float = 0.1  # peak search window around the predicted shift ...
    search_speed_m_s: float = 1.5  # ... widened to this speed times the time since the last match
    max_coast_s: float = 1.0  # frames without a trusted pose for longer than this: restart (reset)
    map_keyframes: int = 16  # keys kept for re-use (onboard/nislam/keymap.py); 0: every new key is new
    reuse_max_angle_deg: float = 25.0  # a kept key is tried when its optical axis is this close ...
    reuse_max_dist_m: float = 0.5  # ... and its position this close to the frame's
    reuse_candidates: int = 2  # kept keys tried per weakening match, the most alike in view first
    # Every n-th firm match is also measured against the kept key most alike
    # in view, after the pose went out, and the key positions solved again
    # (KeyframeMap.link): the keys agree before one is re-used; 0 = only at re-uses.
    link_every_n_frames: int = 5
    reuse_reset_jump_m: float = 0.05  # a re-use moving the position this much beyond what it may have flown: reset
    # Eq. 18 weighted by the inverse variance of each depth difference (sensor
    # noise sigma_rel z^2, at least the floor, plus the slope times the cell
    # sampling) and carried to the sub-cell peak; floor 0 = the paper's mean.
    depth_sigma_rel: float = 0.0015  # 1/m: stereo / structured-light class (1.5 mm at 1 m)
    # Each depth difference carried to the sub-cell peak along the key's depth
    # slope: at the whole-cell shift the rounding times the slope moved t_z by
    # up to 1 cm a frame on grazing surfaces (docs/nislam-error-budget.md)
    depth_subcell: bool = True
    # Eq. 19's key refinement with the frame's depth carried to the sub-cell
    # peak and gated like Eq. 18: at the whole-cell shift and ungated the
    # key's depth drifted on slanted surfaces and edges, and every later t_z
    # inherited it (docs/nislam-error-budget.md, "The axial part, split")
    depth_refine_subcell: bool = False
    # A cell's depth: the mean of the points within this + 3 depth_sigma_rel z^2
    # of its nearest (the front surface); 0 = the nearest point's, biased
    # toward the camera under depth noise by a share of sigma that follows
    # the points per cell (docs/nislam-error-budget.md, "The axial part, split"):
    # a key at every pixel holds about four times its frames' points per cell
    depth_front_mean_m: float = 0.02
    depth_cell_step: int = 2
    # ... but every cell where the sensor noise leaves t_z more uncertain than
    # this on the sampled ones (far, sparse views; docs/nislam-error-budget.md,
    # "The axial part, split"); 0 = never
    depth_all_cells_sd_m: float = 0.0  # Eq. 18 over every n-th row and column (1: 10-15 % less axial noise, +1.7 ms)
    # The depth gate (gate_depth_m around the median) widened to this many
    # sigma of each difference's sensor noise (weighted fit only): far cells'
    # noise is cut symmetrically about the true t_z, not about the median's
    # error (docs/nislam-error-budget.md, "The axial part, split"); 0 = fixed
    depth_gate_sigmas: float = 4.0
    depth_slope_limited: bool = False  # carry along the minmod slope, its one-sided spread in the variance (kernels._limited_slope)
    depth_sigma_floor_m: float = 0.001  # floor (depth quantisation, ~1 mm); 0 = unweighted (docs/nislam-error-budget.md)
    # A frame whose depth was captured at another instant than its colour
    # (RgbdFrame.depth_t_s): its geometry taken at the depth's attitude, its
    # gray through the rotation in between (tracker._track)
    depth_time_compensation: bool = True
    # Colour rows exposed one after another over this time (top first); 0 = a
    # global shutter, -1 = the camera's (CameraIntrinsics.readout_s). Each row is
    # rotated to the middle row's instant (onboard/nislam/shutter.py,
    # docs/nislam-error-budget.md).
    rolling_shutter_readout_s: float = -1.0
    # ... with the body rate from the attitude at t +- this: wider than the
    # calibration's, a noisy AHRS's rate over +-20 ms is mostly noise (1 deg
    # white: ~35 deg/s) and the correction would carry it into every row.
    rolling_shutter_rate_half_window_s: float = 0.05
    # t_z on the key axis from a plane fit of the depth differences: off, its
    # tilt is noise levered onto t_z (docs/nislam-error-budget.md)
    depth_tilt_fit: bool = False
    depth_tilt_max_rad: float = 0.026  # ~1.5 deg: larger tilts are fit failures
    # Eq. 17's new key made from the last frame matched firmly (PSR >= T_r) on
    # the key instead of the frame whose PSR fell below T_r: better on the
    # Kinect's tum_fr1_rpy, worse on most synthetic flights (fewer frames of
    # overlap, more keys), so off (docs/nislam-error-budget.md, "The new key
    # from the last firm frame"). The fused tracker always keeps the paper's.
    key_from_last_firm_frame: bool = False
    calibrate_time_offset: bool = True  # estimate the attitude time offset online
    calibrate_every_n_frames: int = 4  # residual-rotation fit for the calibration on every n-th frame
    calibrate_settle_updates: int = 200  # ... but on every frame until this many updates
    layer_min_gap_m: float = 0.2  # depth relief (2 x std) the residual rotation needs
    layer_downsample: int = 4  # the residual rotation is fitted on blocks of n x n cells
    layer_min_cover: float = 0.2  # a block takes part when this share of its cells is filled in both
    time_offset_s: float = 0.0  # initial attitude time offset: attitude is queried at t + offset
    time_offset_max_s: float = 0.1
    time_offset_forget: float = 0.999  # per-update forgetting: a hardware constant, ~1000 updates of memory
    rate_half_window_s: float = 0.02  # angular rate from attitude at t +- this
    # White-noise sd of the AHRS attitude per axis [deg]: the reported lateral
    # variance grows by 2 (depth x sd)^2 (onboard/nislam/attitude_var.py).
    # 0.1: myAHRS+ class (the simulator's `myahrs` profile); 0.05 for an
    # autopilot's EKF attitude; 0 for an exact attitude. A replay adding
    # `--attitude-noise-deg N` adds N in quadrature (onboard.fusion.registry).
    attitude_sd_deg: float = 0.1
