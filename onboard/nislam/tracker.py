"""NI-SLAM tracker: attitude from an AHRS, translation from a kernel correlation
filter on axonometric images (Wang, Yuan, Xie, "Non-Iterative SLAM", ICAR 2017).

A pure core: arrays in, a `TrackResult` out; no threads, no I/O, no logging
setup. Equation numbers refer to the paper; section numbers of
`reference-nislam.md` (the authors' code) are given as "ref. §n".

Per frame (ref. "Per-frame order"):
  1. attitude R_W_C at the capture time (+ the calibrated time offset),
  2. rotate the cloud into the key camera's axes and project it (Sec. IV-A),
  3. correlation response, sub-cell peak, PSR (Eqs. 14-16),
  4. depth translation over well-matched cells (Eq. 18) and the residual
     rotation from the tilt of the depth differences; pose composition,
  5. key refinement by a count-weighted moving average (Eq. 19),
  6. a new key frame when PSR < T_r (Eq. 17).
Steps 5 and 6 serve the next frames, not this one's pose: `track()` only
queues them and `finish_frame()` does them, once the caller has sent the
pose (the next `track()` does them first if it was not called).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Callable

import numpy as np

from onboard.core import attitude_smoothing
from onboard.core.camera import CameraIntrinsics
from onboard.core.messages import AttitudeSource, KeyframeCloud, RgbdFrame, TrackResult, TrackState
from onboard.nislam import kernels as kern
from onboard.nislam.attitude_var import attitude_lateral_var_m2, with_attitude_var
from onboard.nislam.calibration import OffsetCalibration, RotationResidual, body_rate
from onboard.nislam.correlation import KernelCorrelationFilter, Peak, find_peak, whiten
from onboard.nislam.deferred import Deferred
from onboard.nislam.depth import depth_translation
from onboard.nislam.keymap import KeyframeMap, Measured
from onboard.nislam.keys import Key, KeyStore
from onboard.nislam.matched import Match, Prev, pose_from_match
from onboard.nislam.params import NislamParams
from onboard.nislam.projection import (
    AxonometricImage,
    Cloud,
    adaptive_resolution,
    project,
)
from onboard.nislam.results import lost_result, quality_from_psr, restart_result
from onboard.nislam.sampling import frame_cloud, key_cloud, match_cloud

log = logging.getLogger(__name__)


class NislamTracker:
    """NI-SLAM tracking front end (one instance per camera)."""

    name = "nislam"

    def __init__(self, intrinsics: CameraIntrinsics, params: NislamParams = NislamParams()):
        if params.rolling_shutter_readout_s < 0:  # the camera's own (0: a global shutter)
            params = dataclasses.replace(params, rolling_shutter_readout_s=intrinsics.readout_s)
        self.intr = intrinsics
        self.p = params
        self.shape = (params.grid_height, params.grid_width)
        self._key: Key | None = None
        # The kept keys and one more: a new key is made before the map lets one go.
        self._store = KeyStore(self.shape, max(params.map_keyframes, 1) + 1)
        self._map: KeyframeMap[Key] = KeyframeMap(
            params.map_keyframes, on_evict=lambda key: self._store.give_back(key.slot))
        self._prev: Prev | None = None
        self._next_key_id = 0
        self._reset_counter = 0
        self._lost = False
        self._last_trusted_p: np.ndarray | None = None
        self._frame_count = 0
        self._calib = OffsetCalibration(params.time_offset_forget, params.time_offset_max_s,
                                        params.time_offset_s)
        self._deferred = Deferred()  # steps 5 and 6, for after the pose (deferred.py)
        self._reused_after_pose: int | None = None  # the kept key re-used after the last pose
        # A cell's depth: the mean of its front surface's points (kernels.zbuffer_project)
        self._front = (params.depth_front_mean_m, 3.0 * params.depth_sigma_rel
                       if params.depth_front_mean_m > 0 else 0.0)
        kern.warm_up()  # compile before the first frame, not during it
        attitude_smoothing.warm_up()  # the attitude's local fit, which rotation_at runs

    # ------------------------------------------------------------------ API
    @property
    def attitude_offset_s(self) -> float:
        return self._offset_s()

    def _offset_s(self) -> float:
        """The calibrated offset, after a residual fit still queued (_match)."""
        self._deferred.run(self._calib)
        return self._calib.offset_s

    def finish_frame(self) -> None:
        """The last frame's work that its pose did not need (its key's
        refinement, Eq. 19; the new key's projection, filter and map entry,
        Eq. 17): called after the pose went out. The same operations in the
        same order as if done inside track(), so the poses are identical."""
        while self._deferred:  # a re-use's matches queue the re-used key's refinement
            self._deferred.run()

    def track(self, frame: RgbdFrame, attitude: AttitudeSource) -> TrackResult:
        """Track one frame (`_track`), after the last frame's deferred work."""
        self.finish_frame()  # the last frame's, if the caller did not
        reused_key, self._reused_after_pose = self._reused_after_pose, None
        result = self._track(frame, attitude, reused_key)
        return result if reused_key is None else dataclasses.replace(result, keyframe_withdrawn=True)

    def _track(self, frame: RgbdFrame, attitude: AttitudeSource, reused_key: int | None) -> TrackResult:
        """Track one frame; attitude is looked up at the capture time + offset.

        A frame whose depth was captured at another instant than its colour
        (`depth_t_s`) takes its geometry at the depth's attitude and its gray
        through the rotation between the two (projection.make_cloud), so a
        Kinect pairing up to 20 ms apart, its depth captured 20 ms before its
        stamp, does not shift the texture against the geometry by the rotation
        in between (at 60 deg/s, 0.4 deg a frame: ~10 mm at 1.5 m). The result
        keeps the frame's stamp and its colour-time attitude."""
        offset_s = self._calib.offset_s  # the one this frame is tracked with (and reports)
        t_att = frame.t_s + offset_s
        r_cur = attitude.rotation_at(t_att)
        if r_cur is None or not np.all(np.isfinite(r_cur)):
            return self._lost_result(frame.t_s, "no attitude")
        r_g, r_cd = r_cur, None  # the geometry's attitude, its rotation from the colour's
        if self.p.depth_time_compensation and frame.depth_t_s is not None \
                and abs(frame.depth_t_s - frame.t_s) > 1e-4:
            r_d = attitude.rotation_at(frame.depth_t_s + offset_s)
            if r_d is not None and np.all(np.isfinite(r_d)):  # else: as if taken with the colour
                # Every other look-up stays at the colour's instant; the frame and
                # its key keep the geometry's rotation from it (r_geom), so a
                # key's attitude looked up again is its projection's.
                r_g, r_cd = r_d, r_cur.T @ r_d
        # The key's pixel step: key and frame sampled alike (Key.stride).
        stride = self.p.pixel_stride if self._key is None or self._lost else self._key.stride
        remake = functools.partial(frame_cloud, frame, r_cd=r_cd, intr=self.intr, p=self.p,
                                   attitude=attitude, t_att=t_att)
        cloud = remake(stride)
        min_points = self.p.min_valid_fraction * self.shape[0] * self.shape[1]
        if len(cloud) < min_points:
            return self._lost_result(frame.t_s, "too few depth pixels")
        if self._key is None or self._lost or self._coasted_too_long(frame.t_s):
            return self._restart(frame.t_s, r_cur, cloud, r_g, r_cd, remake)
        key = self._key
        finished: list[KeyframeCloud] = []
        outcome = self._match(key, cloud, frame.t_s, r_g, attitude, t_att)
        reused = False
        if outcome is None or outcome.peak.psr < self.p.psr_keyframe:
            # A failed or weakened match (it may have slid off the true
            # shift, as on blank-turn and yaw-spin): the kept keys are tried
            # before the pose, which takes a firm one's match.
            found = self._reuse(key, outcome, cloud, frame.t_s, r_g, attitude, t_att)
            if found is not None:
                finished.append(self._key_cloud(key))
                key, outcome = found
                reused = True
                self._count_jump(outcome.p_W_m, frame.t_s)
        from_previous = outcome is None and self._prev is not None and self._prev.t_s > key.t_s
        if from_previous:
            # The current frame no longer matches the key: make the last trusted
            # frame the key (it matched, so it overlaps both) and try again.
            finished += self._new_key_from(self._prev)
            key = self._key
            outcome = self._match(key, cloud, frame.t_s, r_g, attitude, t_att)
        if outcome is None:
            self._lost = True
            lost = self._lost_result(frame.t_s, "correlation peak too weak", tuple(finished))
            return dataclasses.replace(lost, keyframe_from_previous=from_previous)

        if key.keyframe_id == reused_key and not reused:
            # The first frame on a key re-used after the last pose: its step
            # from the last position reported is the re-use's jump, judged as
            # an in-place re-use's is (less the distance flown in between).
            self._count_jump(outcome.p_W_m, frame.t_s)
        peak = outcome.peak
        before = self._prev
        self._prev = Prev(frame.t_s, cloud, r_g, key, outcome.p_W_m - key.p_W_m,
                           outcome.pose_var[:3], r_cd, remake)
        self._last_trusted_p = outcome.p_W_m
        new_key = peak.psr < self.p.psr_keyframe  # Eq. 17 (no kept key matched firmly)
        leaving = not new_key and key.leaving_grid(self.p.min_valid_fraction)
        key_id = self._key.keyframe_id
        n_link = self.p.link_every_n_frames
        if n_link > 0 and not (new_key or leaving or reused) and self._frame_count % n_link == 0:
            self._deferred.add(None, lambda: self._link(key, outcome, cloud, frame.t_s, r_g,
                                                        attitude, t_att))
        if new_key or leaving:
            # The switching frame is posed against the old key, then becomes the
            # key with that pose (ref. "Per-frame order", step 6): made after
            # the pose went out (finish_frame); the old key's cloud goes now.
            # A frame still matched firmly but leaving the key's grid tries
            # the kept keys first, after its pose too: its pose does not
            # depend on them.
            finished.append(self._key_cloud(self._key))
            key_id = self._next_key_id
            prev = self._prev
            if new_key and self.p.key_from_last_firm_frame and not reused \
                    and before is not None and before.base is key:
                prev = before  # matched firmly on this key: the better pose to start from
            if new_key:
                self._deferred.add(None, lambda: self._new_key_from(prev, hand_over=False))
            else:
                self._deferred.add(None, lambda: self._reuse_or_new_key(
                    key, outcome, prev, attitude, t_att))
        att_var = attitude_lateral_var_m2(outcome.depth.z_mean_m, self.p.attitude_sd_deg)
        return TrackResult(
            t_s=frame.t_s,
            state=TrackState.TRACKING,
            trusted=True,
            p_W_m=outcome.p_W_m,
            R_W_C=r_cur,
            pose_var=with_attitude_var(outcome.pose_var, key.R_W_C, att_var),
            quality=quality_from_psr(peak.psr, self.p.psr_lost, self.p.psr_refine),
            psr=peak.psr,
            keyframe_id=key_id,
            new_keyframe=new_key or leaving,
            reset_counter=self._reset_counter,
            lost_reason=None,
            shift_cells=(peak.du_cells, peak.dv_cells),
            tz_m=outcome.depth.tz_m,
            res_m=key.img.res_m,
            rotation_residual_rad=outcome.theta_rad,
            attitude_offset_s=offset_s,
            matched_cells=outcome.depth.matched,
            finished_keyframes=tuple(finished),
            keyframe_reused=reused or key.keyframe_id == reused_key,
            keyframe_from_previous=from_previous,
            reference_keyframe_id=key.keyframe_id,
            reference_offset_m=outcome.p_W_m - key.p_W_m,
            attitude_var_m2=att_var,
        )

    def _count_jump(self, p_W_m: np.ndarray, t_s: float) -> None:
        """A re-used key (and the refined key positions) can move the
        position by more than the flight controller should take as motion,
        e.g. back onto the old keys after a restart: such a jump bumps the
        reset counter so the estimator re-anchors instead of rejecting it.
        The jump is measured from the last position reported, less the
        distance the camera may have flown since (`search_speed_m_s`), not
        from the weakened match against the old key: that match is often a
        wrong peak and is never reported."""
        if self._last_trusted_p is None or self._prev is None:
            return
        jump_m = float(np.linalg.norm(p_W_m - self._last_trusted_p))
        flown_m = self.p.search_speed_m_s * max(t_s - self._prev.t_s, 0.0)
        if jump_m - flown_m > self.p.reuse_reset_jump_m:
            self._reset_counter += 1
            log.info("key re-use moved the position by %.3f m: reset %d", jump_m,
                     self._reset_counter)

    def _coasted_too_long(self, t_s: float) -> bool:
        """No trusted pose for longer than `max_coast_s`: the key is not
        matched again (a window that wide invites a look-alike peak)."""
        return self._prev is not None and t_s - self._prev.t_s > self.p.max_coast_s

    def finish(self) -> KeyframeCloud | None:
        """Flush the current key's refined cloud (end of a run)."""
        self.finish_frame()
        return None if self._key is None else self._key_cloud(self._key)

    # ------------------------------------------------------------ matching
    def _match(
        self, key: Key, cloud: Cloud, t_s: float, r_cur: np.ndarray, attitude: AttitudeSource,
        t_att: float, link: bool = False,
    ) -> Match | None:
        """`link`: a second measurement of a frame already posed (a key link,
        onboard.nislam.keymap): the key's motion prior, refinement and the
        time-offset calibration are left as they are."""
        # The key's attitude is looked up again at the current offset estimate,
        # so key and frame share one clock while the offset settles (a residual
        # fit of an earlier match in this frame first, then its refinement).
        r_key = attitude.rotation_at(key.t_s + self._offset_s())
        self._deferred.run(key)  # its refinement by an earlier match
        if r_key is None:
            r_key = key.R_W_C
        elif key.r_geom is not None:
            r_key = r_key @ key.r_geom  # its geometry's attitude
        r_rel = r_key.T @ r_cur  # R_key^-1 R_cur (ref. §2)
        img = project(cloud, r_rel, self.shape, key.img.res_m, front=self._front)
        covered = float(img.mask.mean())
        if covered < self.p.min_valid_fraction:
            return None
        # The search window grows with the time since the last match, so a
        # stalled loop or dropped frames widen it instead of losing the key.
        radius_m = max(self.p.search_radius_m, self.p.search_speed_m_s * key.since_last_match_s(t_s))
        peak = find_peak(
            key.filt.response(whiten(img.gray, img.mask)), self.p.psr_exclude_cells, key.predicted_shift(t_s),
            max(3, int(radius_m / key.img.res_m)), self.p.peak_lobe_centroid,
        )
        if not peak.psr >= self.p.psr_lost:  # also catches NaN
            return None
        du, dv = int(round(peak.du_cells)), int(round(peak.dv_cells))
        depth = depth_translation(key, img, du, dv, self.p,
                                  (peak.du_cells - du, peak.dv_cells - dv))
        if depth is None:
            return None
        if link:
            return pose_from_match(key, peak, depth, np.zeros(3))
        self._frame_count += 1
        # Calibrate on every frame until the offset has settled, then sparsely.
        settling = self._calib.n < self.p.calibrate_settle_updates
        every = 1 if settling else self.p.calibrate_every_n_frames
        theta_img = np.zeros(3)
        if key.layers is not None and self._frame_count % every == 0:
            # The residual fit (a sixth of a match) only when the estimate can
            # use it: with the key's and the frame's rates alike (g ~ 0: a
            # hover, a steady turn) it says nothing about time. The pose does
            # not use it either (it moves the offset for the next lookups):
            # queued before the refinement, which changes the key layers it reads.
            g = self._rate_difference(key, r_rel, attitude, t_att)
            if g is not None and self._calib.informative(g[:2]):
                self._deferred.add(self._calib, lambda: self._fit_residual(
                    key, img, peak, depth.tz_m, g, theta_img))
        if peak.psr > self.p.psr_refine:  # for the next frames: after the pose
            frac = (peak.du_cells - du, peak.dv_cells - dv)
            self._deferred.add(key, lambda: self._refine(key, img, du, dv, depth.tz_m, frac))
        key.shifts = [*key.shifts[-1:], (t_s, peak.du_cells, peak.dv_cells)]
        key.coverage = [*key.coverage[-1:], covered]
        return pose_from_match(key, peak, depth, theta_img)

    def _fit_residual(self, key: Key, img: AxonometricImage, peak: Peak, tz_m: float,
                      g: np.ndarray, theta_out: np.ndarray) -> None:
        """The colour layers' residual rotation into the offset calibration;
        written into the frame's `rotation_residual_rad` (`theta_out`) too."""
        theta = key.layers.residual(img, (peak.du_cells, peak.dv_cells), tz_m, self.p)
        if theta is not None:
            theta_out[:] = theta
            self._calib.update(g[:2], theta[:2])

    def _link(self, key: Key, outcome: Match, cloud: Cloud, t_s: float, r_cur: np.ndarray,
              attitude: AttitudeSource, t_att: float) -> None:
        """The frame, firmly matched against `key`, matched against the kept
        key most alike in view too (KeyframeMap.link): after the pose went out."""

        def measure(other: Key) -> Measured | None:
            kept, other.shifts = other.shifts, []  # its prior is stale: search it all
            o = self._match(other, cloud, t_s, r_cur, attitude, t_att, link=True)
            other.shifts = kept
            return None if o is None else Measured(o.p_W_m, o.pose_var[:3], o.peak.psr)

        self._map.link(key, Measured(outcome.p_W_m, outcome.pose_var[:3], outcome.peak.psr),
                       r_cur, self.p.reuse_max_angle_deg, self.p.reuse_max_dist_m,
                       self.p.psr_keyframe, measure)

    def _reuse(
        self, key: Key, outcome: Match | None, cloud: Cloud, t_s: float, r_cur: np.ndarray,
        attitude: AttitudeSource, t_att: float,
    ) -> tuple[Key, Match] | None:
        """The match against the current key weakened (PSR < T_r) or failed:
        try the kept keys that look the same way from about the same place,
        and make the best one that matches at least as firmly as a fresh key
        would (PSR >= T_r) the current key again. A frame matched against both
        keys measures their offset: the key positions are refined from all
        offsets measured so far (onboard.nislam.keymap)."""
        p_guess = outcome.p_W_m if outcome is not None else self._prev.p_W_m  # type: ignore[union-attr]
        best: tuple[Key, Match] | None = None
        for cand in self._map.candidates(
            r_cur, p_guess, key.keyframe_id, self.p.reuse_max_angle_deg, self.p.reuse_max_dist_m,
            self.p.reuse_candidates,
        ):
            cand.shifts, cand.coverage = [], []  # not matched for a while: search it all
            o = self._match(cand, cloud, t_s, r_cur, attitude, t_att)
            if o is not None and o.peak.psr >= self.p.psr_keyframe:
                if best is None or o.peak.psr > best[1].peak.psr:
                    best = (cand, o)
        if best is None:
            return None
        cand, o = best
        d_cand = o.p_W_m - cand.p_W_m
        if outcome is not None:
            d_key = outcome.p_W_m - key.p_W_m
            self._map.add_offset(key.keyframe_id, cand.keyframe_id, d_key - d_cand,
                                 outcome.pose_var[:3] + o.pose_var[:3])
            self._map.solve()
        self._key = cand
        self._map.use(cand)
        return cand, dataclasses.replace(o, p_W_m=cand.p_W_m + d_cand)

    def _reuse_or_new_key(self, key: Key, outcome: Match, prev: Prev,
                          attitude: AttitudeSource, t_att: float) -> None:
        """After the pose of a frame leaving its key's grid (`Key.leaving_grid`):
        a kept key that matches it firmly becomes the key again (the next
        frame says `keyframe_reused` and `keyframe_withdrawn`), otherwise the
        frame becomes the key (Eq. 17). The key id the frame announced is used
        up either way, so an id never names two keys."""
        found = self._reuse(key, outcome, prev.cloud, prev.t_s, prev.R_W_C, attitude, t_att)
        if found is None:
            self._new_key_from(prev, hand_over=False)
            return
        self._next_key_id += 1
        cand, o = found
        self._prev = Prev(prev.t_s, prev.cloud, prev.R_W_C, cand, o.p_W_m - cand.p_W_m,
                           o.pose_var[:3], prev.r_geom, prev.remake)
        self._reused_after_pose = cand.keyframe_id

    def _rate_difference(
        self, key: Key, r_rel: np.ndarray, attitude: AttitudeSource, t_att: float
    ) -> np.ndarray | None:
        """g = omega_key - R_rel omega_cur in key axes (rad/s), see OffsetCalibration."""
        w_cur = body_rate(attitude, t_att, self.p.rate_half_window_s)
        w_key = body_rate(attitude, key.t_s + self._offset_s(), self.p.rate_half_window_s)
        if w_cur is None or w_key is None:
            return None
        return w_key - r_rel @ w_cur

    def _refine(self, key: Key, img: AxonometricImage, du: int, dv: int, tz: float,
                frac: tuple[float, float] = (0.0, 0.0)) -> None:
        key.refine(img, du, dv, tz, frac, self.p.depth_refine_subcell, self.p.gate_depth_m)

    # ----------------------------------------------------------- key frames
    def _restart(
        self, t_s: float, r_cur: np.ndarray, cloud: Cloud, r_g: np.ndarray,
        r_cd: np.ndarray | None, remake: Callable[[int], Cloud] | None = None,
    ) -> TrackResult:
        """First key, or a new key after a lost spell placed at the last trusted
        position in the same world frame (the reset counter marks the jump).
        `r_g`: the attitude of the cloud's geometry, `r_cd` its rotation from
        the attitude at t_s (None: the same)."""
        p_W = np.zeros(3) if self._last_trusted_p is None else self._last_trusted_p.copy()
        if self._key is not None:
            self._reset_counter += 1
        self._lost = False
        self._prev = Prev(t_s, cloud, r_g, None, p_W, np.zeros(3), r_cd, remake)
        finished = self._new_key_from(self._prev)
        self._last_trusted_p = p_W
        return restart_result(t_s, p_W, r_cur, self._key, self._reset_counter,
                              self._offset_s(), tuple(finished))

    def _new_key_from(self, prev: Prev, hand_over: bool = True) -> list[KeyframeCloud]:
        """Project `prev` un-rotated at an adapted resolution and train on it;
        returns the replaced key's cloud for the map (`hand_over`). A key made
        inside track() (the first, a restart, a failed match) is matched at
        once, but its colour only serves the map: gathered after the pose."""
        old = self._key
        finished = [] if old is None or not hand_over else [self._key_cloud(old)]
        p = self.p
        res = adaptive_resolution(
            prev.cloud, p.grid_width, p.adaptive_mu, p.max_distance_m, p.len_hist, p.hist_sample,
            self.intr.height / self.intr.width,
        )
        cloud = key_cloud(prev.cloud, prev.remake, res, self.intr.fx, p)
        fine = match_cloud(cloud, prev.remake, p)  # Eq. 18's and the map's (key_depth_stride)
        slot = self._store.take()
        colour_later = hand_over  # False only for the Eq. 17 key, made after the pose already
        fine_img = project(fine, np.eye(3), self.shape, res, with_colour=not colour_later,
                           front=self._front)
        # Its own projection (what its frames look like) trains the filter and the layers.
        own = fine_img if fine is cloud else project(cloud, np.eye(3), self.shape, res, front=self._front)
        img = slot.hold(own, fine_img)
        if colour_later:  # the same projection's colour: a third of the key's making
            self._deferred.add(slot.bgr, lambda: np.copyto(slot.bgr, project(
                fine, np.eye(3), self.shape, res, with_colour=True).bgr))
        filt = KernelCorrelationFilter(self.shape, p.kernel_sigma, p.lam, p.label_sigma_cells, slot.spectra)
        filt.train(whiten(img.gray, img.mask))
        layers = RotationResidual.train(img, p) if p.calibrate_time_offset else None
        self._key = Key(
            keyframe_id=self._next_key_id,
            t_s=prev.t_s,
            p_W_m=np.array(prev.p_W_m, dtype=np.float64),
            R_W_C=prev.R_W_C.copy(),
            img=img,
            filt=filt,
            slot=slot,
            layers=layers,
            r_geom=prev.r_geom,
            stride=cloud.stride, as_projected=p.key_depth_stride > 0,
        )
        self._next_key_id += 1
        if self.p.map_keyframes > 0:
            self._map.use(self._key)  # the least recently used beyond capacity goes back
            if prev.base is not None:  # the new key's offset from the key its frame matched
                self._map.add_offset(prev.base.keyframe_id, self._key.keyframe_id, prev.d_W_m,
                                     prev.var_W_m2)
        elif old is not None:
            self._store.give_back(old.slot)
        return finished

    def _key_cloud(self, key: Key) -> KeyframeCloud:
        """The key as it is now: copies, since a kept key may be refined and
        moved after the map consumer got it (same id: the newer one wins),
        and its slot is re-used for a later key."""
        self._deferred.run(key)
        self._deferred.run(key.img.bgr)  # its colour, if gathered later
        return KeyframeCloud(
            key.keyframe_id, key.t_s, key.p_W_m.copy(), key.R_W_C, key.img.res_m,
            np.where(key.count > 0, key.depth_ref, 0.0), key.gray_ref.copy(), key.img.bgr.copy(),
        )

    # -------------------------------------------------------------- results
    def _lost_result(
        self, t_s: float, reason: str, finished: tuple[KeyframeCloud, ...] = ()
    ) -> TrackResult:
        """A frame without a trusted pose. Only a failed match gives up the
        key (self._lost); a frame without attitude or depth is skipped and the
        next one is matched against the same key, its search window widened
        by the time passed (`max_coast_s` bounds how long)."""
        return lost_result(t_s, reason, self._key, self._reset_counter, self._offset_s(),
                           finished)
