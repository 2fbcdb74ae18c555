"""FastORB tracker parameters (the `[fastorb]` configuration section).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class FastOrbParams:
    """Tracker parameters; defaults are the paper's where it gives one, the
    others measured on tum_fr1_rpy (config/default.toml has the figures)."""

    # Pre-processing (Sec. III, Fig. 3)
    clahe_clip_limit: float = 2.0
    clahe_tiles: int = 8  # tiles per image side
    # ORB keypoints as ORB-SLAM2: 1000 over 8 levels at scale 1.2 (Sec. IV-C)
    orb_features: int = 1000
    orb_scale_factor: float = 1.2
    orb_levels: int = 8
    orb_fast_threshold: int = 20
    # Stage one: UAM-seeded pyramid LK (Algorithms 1-2, Eqs. 14-20)
    use_motion_model: bool = True  # false: plain KLT from the old positions (Table I's baseline)
    uam_accel_gain: float = 1.0  # 1: uniform acceleration (Eq. 14); 0: constant velocity
    uam_whole_frames: bool = True  # motion model on whole frame periods, not jittery stamps
    lk_win_px: int = 5  # omega = 2: a 5 x 5 window, k = 25 of Eq. 17
    lk_max_level: int = 2  # 1/4 covers ORB's 1/1.2^7 = 1/3.6 (see fastorb_match.track_lk)
    lk_max_iter: int = 10  # N_itermax of Eq. 20
    lk_eps_px: float = 0.03  # stop when an update moves less than this [px]
    lk_max_error: float = 20.0  # Eq. 19 window residual above this rejects a point [gray]
    lk_min_eigen: float = 1e-4  # OpenCV minEigThreshold: weaker windows are not tracked
    # Stage two: motion smoothness (GMS) and the epipolar constraint (Sec. IV-D)
    gms_grid_cols: int = 16
    gms_grid_rows: int = 12
    gms_alpha: float = 6.0  # GMS threshold tau = alpha sqrt(n)
    epipolar_threshold_px: float = 2.0
    epipolar_confidence: float = 0.99
    # Pose: PnP + RANSAC, then robust refinement
    pnp_reprojection_px: float = 3.0  # RANSAC inlier threshold
    pnp_iterations: int = 100
    pnp_confidence: float = 0.99
    pnp_huber_px: float = 1.0  # Huber-weighted Gauss-Newton [px]; 0 with rgbd_bf_px 0: LM
    rgbd_bf_px: float = 120.0  # disparity residual bf / z (ORB-SLAM2 TUM: 40); 0: pixels only
    rgbd_max_depth_m: float = 3.0  # ... for points closer than this (ORB-SLAM2: 40 b = 3.1 m)
    pnp_sigma_gate: float = 3.0  # final inliers within this many robust sigmas ...
    pnp_min_gate_px: float = 1.5  # ... but at least this far
    max_jump_m: float = 0.2  # a pose this far from the prediction (per frame period) ...
    max_jump_deg: float = 15.0  # ... or turned this far from it is not believed
    max_coast_frames: int = 3  # frames without a believed pose before lost
    rolling_shutter_readout_s: float = -1.0  # colour rows read out over this time, top first; 0: global; -1: the camera's (shutter.py)
    rolling_shutter_rate_sd: float = 0.5  # body rate's change per frame the shear fit allows (1 sd) [rad/s]
    rolling_shutter_settle_landmarks: bool = True  # new landmarks re-made with the poses' central-difference rate after the next pose (landmark_rate.py)
    rolling_shutter_repose: bool = True  # ... and a key frame's from its pose solved again with that rate (no rate fit)
    # Landmarks from depth
    landmark_max_sd_m: float = 0.002  # no new landmarks from a pose placing them worse (1 sd, pose.landmark_sd)
    min_depth_m: float = 0.2
    max_depth_m: float = 6.0
    depth_edge_rel: float = 0.05  # 4x4 depth spread above this share of the depth: no landmark
    min_point_distance_px: float = 8.0  # new keypoints keep this far from followed ones
    # Descriptor-free local-map tracking
    map_track_every: int = 2  # every n-th frame
    map_track_keyframes: int = 1  # from the n key frames nearest in view (one LK call each)
    map_track_max: int = 400  # landmarks per frame at most
    map_track_radius_px: float = 10.0  # LK may move a landmark this far from its projection
    # When tracking thins out
    local_map_min_inliers: int = 100  # below: ORB with descriptors, matched to the local map
    redetect_min_inliers: int = 150  # below: ORB detection only (the paper: 300)
    min_inliers: int = 30  # fewer: no pose
    # Key frames (Sec. III)
    keyframe_max_frames: int = 20  # a key frame at least this often ...
    keyframe_inlier_ratio: float = 0.65  # ... or when inliers fall below this share of the last key's
    keyframe_min_inliers: int = 100  # never from a frame with fewer inliers
    local_map_keyframes: int = 5  # key frames nearest in view forming the local map
    max_keyframes: int = 50  # kept for the local map and re-localisation
    match_radius_px: float = 15.0  # local map: keypoint this close to a landmark's projection
    match_max_hamming: int = 64  # ... and this close in descriptor
    map_match_lk_px: float = 0.0  # >0: matched keypoint moved to LK from the landmark's key frame if this close [px]
    # Lost and re-localisation
    reloc_keyframes: int = 4  # key frames tried per lost frame besides the two newest
    reloc_ratio: float = 0.8  # Lowe's ratio test (no pose prior)
    reloc_min_inliers: int = 40
    lost_reset_frames: int = 30  # re-localisation fails this long: new map (reset_counter + 1)
    init_from_attitude: bool = True  # orient a new map by the attitude source, if it has one
    map_cloud_stride: int = 4  # key-frame clouds from every n-th pixel; 0: none
    # Local mapping (mapping.py, bundle.py): local BA per key frame, in slices after frames
    # Off by default: on the synthetic flights it costs accuracy (docs/fastorb_backend.md).
    # Replay, bench and `nislam run` (its idle time) all run it when on.
    local_ba: bool = False  # true: local mapping and BA between frames (`--local-ba`)
    local_ba_keyframes: int = 6  # the new key frame and its most covisible ones, optimised
    local_ba_fixed_keyframes: int = 4  # other key frames seeing their landmarks, held fixed
    local_ba_depth_sd: float = 0.0015  # depth sd per m^2 of depth (Kinect-like; the sim's) [1/m]
    local_ba_max_points: int = 1000  # landmarks in one BA at most: an LM slice's cost grows with them
    local_ba_pixel_sd: float = 1.0  # sd of a key frame's landmark pixel in the BA [px]
    # Loop closing (loop.py, place.py): per key frame in the back-end slices
    loop_closure: bool = True  # false: no loop detection or correction (`--no-loop-closure`)
