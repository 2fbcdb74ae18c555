"""FastORB tracker: descriptor-free keypoint tracking on RGB-D frames (Fu, Yu,
Wang, Yang, He, Zhang, Mian, "Fast ORB-SLAM without Keypoint Descriptors",
IEEE TIP 2022): the tracking front end; local mapping with local BA
(mapping.py, bundle.py) and loop closing (loop.py, place.py) run in slices
by `backend_step()` between frames.

A pure core: arrays in, a `TrackResult` out; no threads, no I/O. It needs no
attitude sensor: `track()` takes the attitude source for the shared `Tracker`
interface and reads it only to orient a new map (`init_from_attitude`).

Per frame (Sec. III "Tracking", Sec. IV; parts in fastorb_*.py):
  1. gray + adaptive histogram equalisation (CLAHE),
  2. the uniform-acceleration model predicts the pose (Eqs. 14-15) and the
     tracked points' landmarks are projected with it (Eq. 16),
  3. pyramid Lucas-Kanade from those predictions (Algorithm 2, Eqs. 17-20),
  4. grid motion statistics, then RANSAC on the fundamental matrix (IV-D),
  5. landmarks of nearby key frames that came back into view are followed
     by LK from their key frame's image (descriptor-free map tracking),
  6. PnP + RANSAC on landmark/pixel pairs, robust refinement with the
     depth at the tracked pixels as a disparity residual (ORB-SLAM2 RGB-D),
  7. a key frame by the paper's rules (ORB with descriptors, matched to the
     local map of nearby key frames, which also re-poses the frame); the same
     when tracking thins out below local_map_min_inliers; below
     redetect_min_inliers new keypoints by ORB detection alone,
  8. no pose: lost; later frames re-localise against key frames by descriptors.

Poses are T_cw (world -> camera, as OpenCV and the paper). World: the first
camera at the origin, oriented by the attitude source at the first frame if
it has one, else the first camera's axes. A landmark found again keeps its id.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from dataclasses import replace

import cv2
import numpy as np

from onboard.core.camera import CameraIntrinsics
from onboard.core.messages import AttitudeSource, KeyframeCloud, RgbdFrame, TrackResult, TrackState
from onboard.core.rotations import so3_log
from onboard.core.se3 import camera_in_world, inverse, make_pose
from onboard.fastorb import kernels as fastorb_kernels
from onboard.fastorb import refine_kernels
from onboard.fastorb.bundle import BaSettings
from onboard.fastorb.features import Detector, Outcome, Tracked, outcome_result
from onboard.fastorb.keyframing import KeyframeMaking
from onboard.fastorb.landmark_rate import Unsettled
from onboard.fastorb.local_map import CloudGrid, Keyframe, LocalMap
from onboard.fastorb.loop import LoopClosing, LoopSettings, PlaceSettings
from onboard.fastorb.map_tracking import MapTracking
from onboard.fastorb.mapping import LocalMapping, MappingSettings, corrected
from onboard.fastorb.matching import (
    LkSettings,
    epipolar_inliers,
    gms_inliers,
    match_by_ratio,
    track_lk,
)
from onboard.fastorb.motion import FrameClock, predict_uam, project
from onboard.fastorb.params import FastOrbParams
from onboard.fastorb.pose import PnpResult, PnpSettings, landmark_sd, restricted, solve_pnp
from onboard.fastorb.shutter import twist_rate

log = logging.getLogger(__name__)


class FastOrbTracker(KeyframeMaking):
    """FastORB tracking front end (one instance per camera)."""

    name = "fastorb"

    def __init__(self, intrinsics: CameraIntrinsics, params: FastOrbParams = FastOrbParams()):
        if params.rolling_shutter_readout_s < 0:  # the camera's own (0: a global shutter)
            params = replace(params, rolling_shutter_readout_s=intrinsics.readout_s)
        p = params
        self.intr = intrinsics
        self.p = p
        self.K = np.array(
            [[intrinsics.fx, 0.0, intrinsics.cx], [0.0, intrinsics.fy, intrinsics.cy], [0, 0, 1.0]]
        )
        self._size = (intrinsics.width, intrinsics.height)
        self._clahe = cv2.createCLAHE(p.clahe_clip_limit, (p.clahe_tiles, p.clahe_tiles))
        self._detector = Detector(p, self._size)
        self._lk = LkSettings(p.lk_win_px, p.lk_max_level, p.lk_max_iter, p.lk_eps_px,
                              p.lk_max_error, p.lk_min_eigen)
        self._pnp = PnpSettings(p.pnp_reprojection_px, p.pnp_iterations, p.pnp_confidence,
                                huber_px=p.pnp_huber_px, sigma_gate=p.pnp_sigma_gate,
                                min_gate_px=p.pnp_min_gate_px, bf_px=p.rgbd_bf_px)
        self._map = LocalMap(p.max_keyframes, p.local_map_keyframes)
        self.mapping = LocalMapping(
            self._map, self.K, BaSettings(1.0 / p.local_ba_depth_sd, p.max_depth_m,
                                pixel_sigma=p.local_ba_pixel_sd),
            MappingSettings(p.local_ba_keyframes, p.local_ba_fixed_keyframes,
                            max_points=p.local_ba_max_points),
        ) if p.local_ba else None
        self.loops = LoopClosing(self._map, self.K, LoopSettings(place=PlaceSettings(
            depth_sd=p.local_ba_depth_sd)), enabled=p.loop_closure, pnp=self._pnp)
        self._maptrack = MapTracking(p, self.K, self._size, self._detector, self._map, self._lk,
                                     self._pnp)
        self._state = TrackState.INITIALIZING
        self._tracked = Tracked.empty()
        self._prev_gray: np.ndarray | None = None
        self._history: deque[tuple[float, np.ndarray]] = deque(maxlen=3)  # (motion time, T_cw)
        self._clock = FrameClock()
        self._t_motion = 0.0  # the current frame's time for the motion model
        self._xi = np.zeros(6)  # the camera's twist per second now (rolling shutter; shutter.py)
        self._rate: np.ndarray | None = None  # the last posed frame's measured body rate
        self._before_lost: tuple[tuple[float, np.ndarray], ...] = ()  # the motion model's poses
        self._last_T_cw: np.ndarray | None = None
        self._unfinished: Keyframe | None = None  # newest key, cloud not handed over yet
        self._unfinished_grid: CloudGrid | None = None  # ... its cloud but for the pose
        self._deferred: list[Callable[[], None]] = []  # for after the pose (finish_frame)
        self._unsettled: list[Unsettled] = []  # the last posed frame's new landmarks (landmark_rate.py)
        self._keyframe_queued = False
        self._next_keyframe_id = 0
        self._next_landmark_id = 0
        self._frames_since_keyframe = 0
        self._frames_since_map = 0
        self._keyframe_inliers = 0
        self._lost_frames = 0
        self._coasted = 0
        self._reloc_cursor = 0
        self._reset_counter = 0
        fastorb_kernels.warm_up()  # compile (or load) before the first frame, not during it
        refine_kernels.warm_up()

    # ------------------------------------------------------------------ API
    def track(self, frame: RgbdFrame, attitude: AttitudeSource) -> TrackResult:
        """Track one frame (the attitude is read only to orient a new map)."""
        self.finish_frame()  # the last frame's, if the caller has not run it
        gray = self._clahe.apply(cv2.cvtColor(frame.bgr, cv2.COLOR_BGR2GRAY))  # step 1
        t_clock = self._clock(frame.t_s)
        self._t_motion = t_clock if self.p.uam_whole_frames else frame.t_s
        try:
            if self._state is TrackState.INITIALIZING:
                return self._initialise(frame, gray, self._initial_pose(frame.t_s, attitude))
            if self._state is TrackState.LOST:
                return self._relocalise(frame, gray, attitude)
            return self._track(frame, gray)
        finally:
            self._prev_gray = gray

    def backend_step(self) -> bool:
        """One unit of the back end's work (local mapping: build a BA, one
        LM iteration, or apply it; else loop closing: one key frame's query
        and correction), for the idle time after a frame; False when there
        was nothing to do. Never needed for tracking itself."""
        self.finish_frame()
        if self.mapping is not None and not self.mapping.idle:
            correction = self.mapping.step()
        elif not self.loops.idle:
            correction = self.loops.step()
        else:
            return False
        if correction is not None:  # the tracked points and recent poses follow
            self._tracked = corrected(self._tracked, correction)
            back = inverse(correction.delta_W)
            self._history = deque(((t, T @ back) for t, T in self._history), maxlen=3)
        return True

    def finish(self) -> KeyframeCloud | None:
        """End of a run: the newest key frame's cloud."""
        self.finish_frame()
        return self._take_cloud()

    def keyframe_pose(self, keyframe_id: int) -> np.ndarray | None:
        """A key frame's T_cw as now estimated (the final trajectory)."""
        self.finish_frame()
        return self.loops.pose_of(keyframe_id)

    # ------------------------------------------------------------- tracking
    def _track(self, frame: RgbdFrame, gray: np.ndarray) -> TrackResult:
        prior = predict_uam(*zip(*self._history), self._t_motion,
                            self.p.uam_accel_gain)  # step 2, Eqs. 14-15
        self._xi = self._twist()
        moved = self._track_frame_to_frame(gray, prior)  # steps 2-4
        self._frames_since_keyframe += 1
        self._frames_since_map += 1
        if self._frames_since_map >= self.p.map_track_every:  # step 5
            self._frames_since_map = 0
            moved = moved.extended(self._maptrack.map_points(gray, prior, moved))
        outcome = self._pose(moved, prior, frame.depth_m)  # step 6
        n_in = 0 if outcome is None else outcome.inliers
        if n_in < self.p.local_map_min_inliers or self._keyframe_due(n_in):  # step 7
            guess = prior if outcome is None else outcome.T_cw
            kept = Tracked.empty() if outcome is None else outcome.tracked
            found = self._maptrack.local_map(frame, gray, guess, kept, xi=self._xi)
            if found is not None and self._plausible(found.T_cw, prior):
                outcome = found
        if outcome is None:
            log.debug("t=%.3f: no pose from %d followed points", frame.t_s, len(moved))
            return self._coast_or_lose(frame.t_s, prior, moved)
        self._coasted = 0
        self._settle_after_pose(outcome)  # the last frame's new landmarks, with this pose
        self._rate = self._maptrack.rate  # measured by the rows' shear (None: global shutter)
        if self._rate is not None:
            self._xi = np.concatenate([self._rate, self._xi[3:]])
        # Firmness decides only where new landmarks could come: a key frame
        # (keypoints with descriptors) or new keypoints below
        # redetect_min_inliers; most frames need neither (0.4 ms saved).
        firm = ((outcome.features is not None or outcome.inliers < self.p.redetect_min_inliers)
                and self._firm(outcome))
        new_key = (firm and outcome.features is not None
                   and outcome.inliers >= self.p.keyframe_min_inliers)
        if log.isEnabledFor(logging.DEBUG):
            log.debug("t=%.3f: %d followed, %d inliers (rms %.2f px), %.1f mm from the "
                      "prediction%s", frame.t_s, len(moved), outcome.inliers, outcome.pnp.rms_px,
                      1e3 * np.linalg.norm(camera_in_world(outcome.T_cw)[0]
                                           - camera_in_world(prior)[0]),
                      ", key frame" if new_key else (
                          ", local map" if outcome.features is not None else ""))
        finished: tuple[KeyframeCloud, ...] = ()
        if new_key:  # made after the pose (keyframing.py)
            finished = self._keyframe_after_pose(frame, gray, outcome)
        elif firm and outcome.inliers < self.p.redetect_min_inliers:
            self._replenish_after_pose(frame, gray, outcome)
        return self._tracked_result(frame.t_s, outcome, new_key, finished)

    def _twist(self) -> np.ndarray:
        """The camera's twist per second for the rolling shutter: the last
        interval's (constant velocity). Not the UAM prediction's, whose
        acceleration term doubles the poses' noise, nor this frame's pose,
        which the correction itself moves."""
        if len(self._history) < 2:
            return np.zeros(6)
        (t0, T0), (t1, T1) = self._history[-2], self._history[-1]
        xi = twist_rate(T0, T1, t1 - t0)
        if self._rate is not None:  # the last frame's shear-measured rate is fresher
            xi[:3] = self._rate
        return xi

    def _firm(self, outcome: Outcome) -> bool:
        """Whether the pose is firm enough to place new landmarks with: the
        error it puts into a landmark at its inliers' depth (pose.landmark_sd)
        at most landmark_max_sd_m; not the camera position's sd, which is
        loose in fast turns with far points (docs/fastorb_backend.md)."""
        sd = landmark_sd(outcome.T_cw, outcome.pnp.cov, outcome.tracked.xyz_W)
        return bool(np.isfinite(sd) and sd <= self.p.landmark_max_sd_m)

    def _pose(self, moved: Tracked, prior: np.ndarray, depth_m: np.ndarray) -> Outcome | None:
        """PnP + RANSAC and refinement on the followed points; None without a
        fit or when the pose jumps implausibly far from the prediction (e.g.
        tracks dragged along by motion blur)."""
        pnp = self._maptrack.solve(moved.xyz_W, moved.uv, depth_m, prior, self._xi)
        if pnp is None or not self._plausible(pnp.T_cw, prior):
            log.debug("no pose from %d points: %s", len(moved),
                      "PnP failed" if pnp is None else "implausible jump")
            return None
        return Outcome(pnp.T_cw, moved.subset(pnp.inliers), restricted(pnp), None)

    def _plausible(self, T_cw: np.ndarray, prior: np.ndarray) -> bool:
        """Whether a pose stays within max_jump_m / max_jump_deg of the motion
        model's prediction (scaled by the square of the frame steps since the
        last pose). Checked only once the model has three poses to go on."""
        if len(self._history) < 3:
            return True
        steps = max((self._t_motion - self._history[-1][0]) / self._clock.period, 1.0)
        d = T_cw @ inverse(prior)
        angle_deg = float(np.degrees(np.linalg.norm(so3_log(d[:3, :3]))))
        shift_m = float(np.linalg.norm(camera_in_world(T_cw)[0] - camera_in_world(prior)[0]))
        return shift_m <= self.p.max_jump_m * steps**2 and angle_deg <= self.p.max_jump_deg * steps**2

    def _coast_or_lose(self, t_s: float, prior: np.ndarray, moved: Tracked) -> TrackResult:
        """No trustworthy pose: for up to max_coast_frames frames keep the
        points LK followed and let the motion model carry the pose (not
        reported), then give up (lost)."""
        if self._coasted >= self.p.max_coast_frames or len(moved) < self.p.min_inliers:
            return self._lose(t_s, "too few inliers")
        self._coasted += 1
        self._tracked = moved
        self._history.append((self._t_motion, prior))
        return self._unposed(t_s, TrackState.TRACKING, "no pose this frame")

    def _track_frame_to_frame(self, gray: np.ndarray, prior: np.ndarray) -> Tracked:
        """Stages one and two (steps 2-4): the tracked points that LK followed
        from the last frame and that pass the motion-smoothness and epipolar
        checks, at their new pixels."""
        trk = self._tracked
        if len(trk) < self.p.min_inliers or self._prev_gray is None:
            return Tracked.empty()
        guess = self._seed(trk, prior) if self.p.use_motion_model else None  # Eq. 16
        uv, ok = track_lk(self._prev_gray, gray, trk.uv, guess, self._lk)  # Eqs. 17-20
        idx = np.flatnonzero(ok)
        idx = idx[gms_inliers(trk.uv[idx], uv[idx], self._size,
                              (self.p.gms_grid_cols, self.p.gms_grid_rows), self.p.gms_alpha)]
        idx = idx[epipolar_inliers(trk.uv[idx], uv[idx], self.p.epipolar_threshold_px,
                                   self.p.epipolar_confidence)]
        return Tracked(uv[idx], trk.xyz_W[idx], trk.ids[idx])

    def _seed(self, trk: Tracked, prior: np.ndarray) -> np.ndarray:
        """Eq. 16: predicted pixels; points behind the camera keep their old pixel."""
        uv, z = project(self.K, prior, trk.xyz_W)
        return np.where((z > 1e-3)[:, None], uv, trk.uv).astype(np.float32)

    # ------------------------------------------------- start, lost, re-localise
    def _initial_pose(self, t_s: float, attitude: AttitudeSource | None) -> np.ndarray:
        """T_cw of a new map: at the last trusted position (origin at start),
        oriented by the attitude source if it has a reading, else as before."""
        if self._last_T_cw is None:
            p_W, R_W_C = np.zeros(3), np.eye(3)
        else:
            p_W, R_W_C = camera_in_world(self._last_T_cw)
        if self.p.init_from_attitude and attitude is not None:
            r = attitude.rotation_at(t_s)
            if r is not None and np.all(np.isfinite(r)):
                R_W_C = np.asarray(r, np.float64)
        return make_pose(R_W_C.T, -R_W_C.T @ p_W)

    def _initialise(self, frame: RgbdFrame, gray: np.ndarray, T_cw: np.ndarray) -> TrackResult:
        """A new map: this frame is the first key frame, at pose T_cw."""
        self._xi, self._rate = np.zeros(6), None  # no motion known
        feats = self._detector.detect(gray, with_descriptors=True)
        first, _ = self._landmarks(frame, T_cw, feats.uv)
        if len(first) < self.p.keyframe_min_inliers:
            return self._unposed(frame.t_s, TrackState.INITIALIZING, "too few keypoints with depth")
        self._map.clear()
        if self.mapping is not None:
            self.mapping.reset()
        self.loops.reset()
        pnp = PnpResult(T_cw, np.ones(len(first), bool), 0.0, np.diag([1e-8] * 6))
        outcome = Outcome(T_cw, first, pnp, feats)
        finished = self._make_keyframe(frame, gray, outcome)
        self._state = TrackState.TRACKING
        return self._tracked_result(frame.t_s, outcome, True, finished, history_reset=True)

    def _lose(self, t_s: float, reason: str) -> TrackResult:
        self._state = TrackState.LOST
        self._lost_frames = 1
        self._reloc_cursor = 0
        self._tracked = Tracked.empty()
        self._before_lost = tuple(self._history)
        self._history.clear()
        return self._unposed(t_s, TrackState.LOST, reason)

    def _relocalise(
        self, frame: RgbdFrame, gray: np.ndarray, attitude: AttitudeSource
    ) -> TrackResult:
        """Step 8: match this frame's descriptors against the newest key frames
        (no pose prior: ratio test, AP3P RANSAC), then against the local map
        around the pose found. Success re-enters the map with a jump, so
        reset_counter counts it; lost_reset_frames failures in a row start a
        new map at the last trusted pose."""
        self._xi, self._rate = np.zeros(6), None  # no motion known
        feats = self._detector.detect(gray, with_descriptors=True)
        kfs, self._reloc_cursor = self._map.reloc_candidates(self._reloc_cursor,
                                                             self.p.reloc_keyframes)
        for kf in kfs:
            q, t = match_by_ratio(feats.desc, kf.desc, self.p.reloc_ratio, self.p.match_max_hamming)
            pnp = solve_pnp(kf.xyz_W[t], feats.uv[q], self.K, self._pnp,
                            self.p.reloc_min_inliers)
            if pnp is None:
                continue
            found = Tracked(feats.uv[q].astype(np.float32), kf.xyz_W[t], kf.ids[t])
            outcome = self._maptrack.local_map(frame, gray, pnp.T_cw, found.subset(pnp.inliers),
                                            feats)
            if outcome is None or outcome.inliers < self.p.reloc_min_inliers:
                continue
            continues = self._continues(outcome.T_cw)
            self._reset_counter += int(not continues)
            self._state = TrackState.TRACKING
            self._lost_frames = 0
            finished = self._make_keyframe(frame, gray, outcome)
            return self._tracked_result(frame.t_s, outcome, True, finished,
                                        history_reset=not continues)
        self._lost_frames += 1
        if self._lost_frames > self.p.lost_reset_frames:
            self._reset_counter += 1
            return self._initialise(frame, gray, self._initial_pose(frame.t_s, attitude))
        return self._unposed(frame.t_s, TrackState.LOST, "re-localisation failed")

    def _continues(self, T_cw: np.ndarray) -> bool:
        """Whether a re-localised pose continues the trajectory: found within
        max_coast_frames of the last pose (as long as tracking may coast) and
        where the motion model of the poses before the loss puts it, by the
        test every tracked pose passes (_plausible). Then it is no jump (the
        map is the same), so no reset, and the motion model goes on. On
        tum_fr1_rpy one blurred frame lost the track and the next re-localised
        in place: a reset the autopilot had to handle for nothing."""
        if self._lost_frames > self.p.max_coast_frames or len(self._before_lost) < 3:
            return False
        self._history.extend(self._before_lost)
        prior = predict_uam(*zip(*self._history), self._t_motion, self.p.uam_accel_gain)
        if self._plausible(T_cw, prior):
            return True
        self._history.clear()
        return False

    # ---------------------------------------------------------------- results
    def _tracked_result(self, t_s: float, outcome: Outcome, new_key: bool,
                        finished: tuple[KeyframeCloud, ...], history_reset: bool = False,
                        ) -> TrackResult:
        self._tracked = outcome.tracked
        self._last_T_cw = outcome.T_cw
        if history_reset:
            self._history.clear()
        self._history.append((self._t_motion, outcome.T_cw))
        return self._result(t_s, TrackState.TRACKING, outcome, None, new_key, finished)

    def _unposed(self, t_s: float, state: TrackState, reason: str) -> TrackResult:
        return self._result(t_s, state, None, reason, False, ())

    def _result(
        self, t_s: float, state: TrackState, outcome: Outcome | None, reason: str | None,
        new_key: bool, finished: tuple[KeyframeCloud, ...],
    ) -> TrackResult:
        return outcome_result(t_s, state, outcome, reason, new_key, finished,
                              self._newest_keyframe_id(), self._reset_counter,
                              self.p.redetect_min_inliers,
                              *self.loops.result_fields())
