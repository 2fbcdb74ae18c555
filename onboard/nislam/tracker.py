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
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from onboard import kernels as kern
from onboard.correlation import KernelCorrelationFilter, Peak, find_peak
from onboard.frames import (
    AttitudeSource,
    CameraIntrinsics,
    KeyframeCloud,
    RgbdFrame,
    TrackResult,
    TrackState,
)
from onboard.geometry import so3_log
from onboard.keymap import KeyframeMap
from onboard.projection import AxonometricImage, Cloud, adaptive_resolution, make_cloud, project

log = logging.getLogger(__name__)


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
    kernel_sigma: float = 0.2
    lam: float = 0.1
    label_sigma_cells: float = 1.0
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
    map_keyframes: int = 16  # keys kept for re-use (onboard/keymap.py); 0: every new key is new
    reuse_max_angle_deg: float = 25.0  # a kept key is tried when its optical axis is this close ...
    reuse_max_dist_m: float = 0.5  # ... and its position this close to the frame's
    reuse_candidates: int = 2  # kept keys tried per weakening match, the most alike in view first
    reuse_reset_jump_m: float = 0.05  # a re-use moving the position this much beyond what it may have flown: reset
    depth_tilt_fit: bool = True  # t_z on the key axis from a plane fit of the depth differences
    depth_tilt_max_rad: float = 0.026  # ~1.5 deg: larger tilts are fit failures
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


@dataclass
class _KeySlot:
    """The memory of one key frame: its projection, the refined images and
    the filter's spectra (6 MB at 480 x 360), allocated once by `_KeyStore`."""

    gray: np.ndarray
    depth_m: np.ndarray
    mask: np.ndarray
    bgr: np.ndarray
    gray_ref: np.ndarray
    depth_ref: np.ndarray
    count: np.ndarray
    spectra: tuple[np.ndarray, np.ndarray]  # conj(z_hat), alpha_hat

    @classmethod
    def allocate(cls, shape: tuple[int, int]) -> "_KeySlot":
        h, w = shape

        def resident(a: np.ndarray) -> np.ndarray:
            a.fill(0)  # written now, so the pages are resident from the start
            return a

        def grid() -> np.ndarray:
            return resident(np.empty(shape, np.float32))

        def spectrum() -> np.ndarray:
            return resident(np.empty((h, w // 2 + 1), np.complex64))

        return cls(grid(), grid(), grid(), resident(np.empty((h, w, 3), np.uint8)), grid(),
                   grid(), grid(), (spectrum(), spectrum()))

    def hold(self, img: AxonometricImage) -> AxonometricImage:
        """`img` copied into this slot; the refined images start from it."""
        np.copyto(self.gray, img.gray)
        np.copyto(self.depth_m, img.depth_m)
        np.copyto(self.mask, img.mask)
        if img.bgr is not None:
            np.copyto(self.bgr, img.bgr)
        else:
            self.bgr.fill(0)  # not the colour of the slot's previous key
        np.copyto(self.gray_ref, img.gray)
        np.copyto(self.depth_ref, img.depth_m)
        np.copyto(self.count, img.mask)
        return AxonometricImage(self.gray, self.depth_m, self.mask, img.res_m, self.bgr)


class _KeyStore:
    """Memory for the key frames the tracker can hold at once (the kept keys
    and the one being made), allocated when the tracker is built. Key frames
    then never allocate: the process is at its working size from the first
    frame, so a long flight cannot creep towards the companion computer's
    memory limit, and a soak shows any real leak plainly."""

    def __init__(self, shape: tuple[int, int], slots: int) -> None:
        self._free = [_KeySlot.allocate(shape) for _ in range(slots)]

    def take(self) -> _KeySlot:
        if not self._free:
            raise RuntimeError("key store exhausted: a key frame was not given back")
        return self._free.pop()

    def give_back(self, slot: _KeySlot) -> None:
        self._free.append(slot)


@dataclass
class _Key:
    """Key frame state: the learned filter, the refined images and the pose.
    The arrays live in `slot` (see _KeyStore)."""

    keyframe_id: int
    t_s: float
    p_W_m: np.ndarray
    R_W_C: np.ndarray
    img: AxonometricImage  # the key's projection, held in `slot`
    filt: KernelCorrelationFilter
    slot: _KeySlot
    layers: "_RotationResidual | None" = None
    shifts: list[tuple[float, float, float]] = field(default_factory=list)  # last two (t_s, du, dv)

    @property
    def gray_ref(self) -> np.ndarray:
        """Refined gray (count-weighted mean, Eq. 19a)."""
        return self.slot.gray_ref

    @property
    def depth_ref(self) -> np.ndarray:
        """Refined depth."""
        return self.slot.depth_ref

    @property
    def count(self) -> np.ndarray:
        """W_k of Eq. 19b."""
        return self.slot.count

    @property
    def mask0(self) -> np.ndarray:
        """Original key mask W_0."""
        return self.slot.mask

    def predicted_shift(self, t_s: float) -> tuple[float, float]:
        """Constant-velocity prediction of the shift at `t_s` against this key,
        in time rather than frames: after dropped frames it moves as far as
        the camera did."""
        if not self.shifts:
            return (0.0, 0.0)
        t1, u1, v1 = self.shifts[-1]
        if len(self.shifts) == 1:
            return (u1, v1)
        t0, u0, v0 = self.shifts[-2]
        k = (t_s - t1) / (t1 - t0) if t1 > t0 else 1.0
        return (u1 + k * (u1 - u0), v1 + k * (v1 - v0))

    def since_last_match_s(self, t_s: float) -> float:
        return t_s - (self.shifts[-1][0] if self.shifts else self.t_s)


@dataclass
class _RotationResidual:
    """The key image kept to measure the residual rotation of later frames.

    A residual rotation theta shifts content by theta x p, i.e. in proportion
    to depth, while a translation shifts every depth alike. One linearised
    least-squares step over n x n blocks fits both at once: the block shift
    d0 + r (z - z_mean), whose depth rate r is theta as the colour image sees
    it. That is what the attitude time offset must be calibrated against (the
    depth image of a Kinect-class sensor is captured at another instant, so
    the tilt of the depth differences calibrates the wrong clock).

    Only blocks covered in both images whose depths agree take part: where
    near objects hide the far surfaces depends on where the camera stands,
    and a correlation over whole layers was pulled by those moving hole
    outlines (a 20-26 ms offset bias on a synthetic orbit with exact attitude,
    none on a pure yaw spin). The blocks' own depths set the depth rate, so no
    layer means enter it.
    """

    gray: np.ndarray  # the key's gray, depth and mask at full resolution
    depth_m: np.ndarray
    mask: np.ndarray

    @classmethod
    def train(cls, img: AxonometricImage, p: "NislamParams") -> "_RotationResidual | None":
        depths = img.depth_m[img.mask > 0]
        # Without depth relief a rotation cannot be told from a translation.
        if len(depths) < 100 or float(np.std(depths)) < 0.5 * p.layer_min_gap_m:
            return None
        return cls(img.gray, img.depth_m, img.mask)

    def residual(
        self,
        img: AxonometricImage,
        shift_cells: tuple[float, float],
        tz_m: float,
        p: "NislamParams",
    ) -> np.ndarray | None:
        """theta (x, y, 0) in key axes [rad], or None when the fit is not
        determined. The frame's depths are the key's minus t_z."""
        n = p.layer_downsample
        du, dv = int(round(shift_cells[0])), int(round(shift_cells[1]))
        ks, cs = _overlap(img.gray.shape, du, dv)
        if ks is None:
            return None
        # Coverage per block, not per cell, decides what both images hold: two
        # sparse samplings of one surface share few cells but the same blocks.
        key_g, key_z, key_cover = kern.block_means(self.gray[ks], self.depth_m[ks], self.mask[ks], n)
        cur_g, cur_z, cur_cover = kern.block_means(img.gray[cs], img.depth_m[cs], img.mask[cs], n)
        ok = (key_cover >= p.layer_min_cover) & (cur_cover >= p.layer_min_cover)
        ok &= np.abs(cur_z + tz_m - key_z) < p.gate_depth_m
        inner = ok[1:-1, 1:-1] & ok[1:-1, 2:] & ok[1:-1, :-2] & ok[2:, 1:-1] & ok[:-2, 1:-1]
        if inner.sum() < 100:
            return None
        # Mean of both images' central differences: second-order accurate.
        gx = 0.25 * (key_g[1:-1, 2:] - key_g[1:-1, :-2] + cur_g[1:-1, 2:] - cur_g[1:-1, :-2])[inner]
        gy = 0.25 * (key_g[2:, 1:-1] - key_g[:-2, 1:-1] + cur_g[2:, 1:-1] - cur_g[:-2, 1:-1])[inner]
        err = (cur_g[1:-1, 1:-1] - key_g[1:-1, 1:-1])[inner]
        err = err - err.mean()  # an exposure change is not a shift
        z = key_z[1:-1, 1:-1][inner]
        z = z - z.mean()
        if float(np.std(z)) < 0.5 * p.layer_min_gap_m:
            return None
        # cur(q) = key(q - d(q)), d = d0 + r z  =>  err ~ -grad . (d0 + r z).
        a = np.stack([gx, gy, gx * z, gy * z], axis=1).astype(np.float64)
        ata = a.T @ a
        if np.linalg.eigvalsh(ata)[0] < 1e-9 * len(z):
            return None
        _, _, ru, rv = -np.linalg.solve(ata, a.T @ err.astype(np.float64))
        # d s = -(t + theta x p) in cells of res: du grows by -theta_y z,
        # dv by +theta_x z; r is in blocks of n cells per metre.
        s = img.res_m * n
        return np.array([rv * s, -ru * s, 0.0])


@dataclass(frozen=True)
class _DepthFit:
    """Result of the depth step (Eq. 18 and the tilt of the differences)."""

    tz_m: float  # camera translation along the key's optical axis
    theta_rad: np.ndarray  # tilt of the depth differences as a rotation (x, y, 0)
    z_mean_m: float  # mean key depth of the matched cells
    matched: int  # matched cells (every other row and column)
    var_z_m2: float  # scatter of the depth differences over the matched cells


@dataclass(frozen=True)
class _Match:
    """A frame matched against the key: pose and what the result reports."""

    p_W_m: np.ndarray
    peak: Peak
    depth: _DepthFit
    theta_rad: np.ndarray  # residual rotation seen by the colour layers (0 if not measured)
    pose_var: np.ndarray  # (6,) in the world frame


@dataclass
class _Prev:
    """The last trusted frame, kept to seed a new key: its position as an
    offset from the key it was matched against (`base`, None after a
    restart: then the offset is the position), so a refined key position
    carries over."""

    t_s: float
    cloud: Cloud
    R_W_C: np.ndarray
    base: "_Key | None"
    d_W_m: np.ndarray
    var_W_m2: np.ndarray  # (3,) of the offset

    @property
    def p_W_m(self) -> np.ndarray:
        return self.d_W_m if self.base is None else self.base.p_W_m + self.d_W_m


@dataclass
class _OffsetCalibration:
    """Online least squares for the attitude time offset.

    A time error eps makes the residual rotation theta ~ eps * g, with g the
    difference of the key's and the current frame's angular rates in key axes.
    Each frame implies offset_true ~ offset_used - (g . theta) / |g|^2; the
    estimate is the |g|^2-weighted mean of those with exponential forgetting.
    """

    forget: float
    max_s: float
    offset_s: float
    num: float = 0.0
    den: float = 0.0
    n: int = 0

    def update(self, g_rad_s: np.ndarray, theta_rad: np.ndarray) -> None:
        g2 = float(g_rad_s @ g_rad_s)
        if g2 < 0.05:  # below ~13 deg/s the residual says nothing about time
            return
        self.num = self.forget * self.num + g2 * self.offset_s - float(g_rad_s @ theta_rad)
        self.den = self.forget * self.den + g2
        self.n += 1
        if self.n >= 20:
            self.offset_s = float(np.clip(self.num / self.den, -self.max_s, self.max_s))


class NislamTracker:
    """NI-SLAM tracking front end (one instance per camera)."""

    name = "nislam"

    def __init__(self, intrinsics: CameraIntrinsics, params: NislamParams = NislamParams()):
        self.intr = intrinsics
        self.p = params
        self.shape = (params.grid_height, params.grid_width)
        self._key: _Key | None = None
        # The kept keys, and one more: a new key is made before the map lets
        # the least recently used one go.
        self._store = _KeyStore(self.shape, max(params.map_keyframes, 1) + 1)
        self._map: KeyframeMap[_Key] = KeyframeMap(
            params.map_keyframes, on_evict=lambda key: self._store.give_back(key.slot))
        self._prev: _Prev | None = None
        self._next_key_id = 0
        self._reset_counter = 0
        self._lost = False
        self._last_trusted_p: np.ndarray | None = None
        self._frame_count = 0
        self._calib = _OffsetCalibration(
            params.time_offset_forget, params.time_offset_max_s, params.time_offset_s
        )
        kern.warm_up()  # compile before the first frame, not during it

    # ------------------------------------------------------------------ API
    @property
    def attitude_offset_s(self) -> float:
        return self._calib.offset_s

    def track(self, frame: RgbdFrame, attitude: AttitudeSource) -> TrackResult:
        """Track one frame; attitude is looked up at the capture time + offset."""
        t_att = frame.t_s + self._calib.offset_s
        r_cur = attitude.rotation_at(t_att)
        if r_cur is None or not np.all(np.isfinite(r_cur)):
            return self._lost_result(frame.t_s, "no attitude")
        cloud = make_cloud(
            frame.bgr, frame.depth_m, self.intr, self.p.min_depth_m, self.p.max_depth_m,
            self.p.pixel_stride,
        )
        min_points = self.p.min_valid_fraction * self.shape[0] * self.shape[1]
        if len(cloud) < min_points:
            return self._lost_result(frame.t_s, "too few depth pixels")
        if self._key is None or self._lost or self._coasted_too_long(frame.t_s):
            return self._restart(frame.t_s, cloud, r_cur)

        key = self._key
        finished: list[KeyframeCloud] = []
        outcome = self._match(key, cloud, frame.t_s, r_cur, attitude, t_att)
        reused = False
        if outcome is None or outcome.peak.psr < self.p.psr_keyframe:
            found = self._reuse(key, outcome, cloud, frame.t_s, r_cur, attitude, t_att)
            if found is not None:
                finished.append(self._key_cloud(key))
                key, outcome = found
                reused = True
                self._count_jump(outcome.p_W_m, frame.t_s)
        if outcome is None and self._prev is not None and self._prev.t_s > key.t_s:
            # The current frame no longer matches the key: make the last trusted
            # frame the key (it matched, so it overlaps both) and try again.
            finished += self._new_key_from(self._prev)
            key = self._key
            outcome = self._match(key, cloud, frame.t_s, r_cur, attitude, t_att)
        if outcome is None:
            self._lost = True
            return self._lost_result(frame.t_s, "correlation peak too weak", tuple(finished))

        peak = outcome.peak
        self._prev = _Prev(frame.t_s, cloud, r_cur, key, outcome.p_W_m - key.p_W_m,
                           outcome.pose_var[:3])
        self._last_trusted_p = outcome.p_W_m
        new_key = peak.psr < self.p.psr_keyframe  # Eq. 17
        if new_key:
            # The switching frame is posed against the old key, then becomes the
            # key with that pose (ref. "Per-frame order", step 6).
            finished += self._new_key_from(self._prev)
        return TrackResult(
            t_s=frame.t_s,
            state=TrackState.TRACKING,
            trusted=True,
            p_W_m=outcome.p_W_m,
            R_W_C=r_cur,
            pose_var=outcome.pose_var,
            quality=self._quality(peak.psr),
            psr=peak.psr,
            keyframe_id=self._key.keyframe_id,
            new_keyframe=new_key,
            reset_counter=self._reset_counter,
            lost_reason=None,
            shift_cells=(peak.du_cells, peak.dv_cells),
            tz_m=outcome.depth.tz_m,
            res_m=key.img.res_m,
            rotation_residual_rad=outcome.theta_rad,
            attitude_offset_s=self._calib.offset_s,
            matched_cells=outcome.depth.matched,
            finished_keyframes=tuple(finished),
            keyframe_reused=reused,
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
        return None if self._key is None else self._key_cloud(self._key)

    # ------------------------------------------------------------ matching
    def _match(
        self, key: _Key, cloud: Cloud, t_s: float, r_cur: np.ndarray, attitude: AttitudeSource,
        t_att: float,
    ) -> _Match | None:
        # The key's attitude is looked up again at the current offset estimate,
        # so key and frame share one clock while the offset settles.
        r_key = attitude.rotation_at(key.t_s + self._calib.offset_s)
        r_key = key.R_W_C if r_key is None else r_key
        r_rel = r_key.T @ r_cur  # R_key^-1 R_cur (ref. §2)
        img = project(cloud, r_rel, self.shape, key.img.res_m)
        if img.mask.sum() < self.p.min_valid_fraction * img.mask.size:
            return None
        # The search window grows with the time since the last match, so a
        # stalled loop or dropped frames widen it instead of losing the key.
        radius_m = max(self.p.search_radius_m, self.p.search_speed_m_s * key.since_last_match_s(t_s))
        peak = find_peak(
            key.filt.response(_whiten(img)), self.p.psr_exclude_cells, key.predicted_shift(t_s),
            max(3, int(radius_m / key.img.res_m)),
        )
        if not peak.psr >= self.p.psr_lost:  # also catches NaN
            return None
        du, dv = int(round(peak.du_cells)), int(round(peak.dv_cells))
        depth = self._depth_translation(key, img, du, dv)
        if depth is None:
            return None
        self._frame_count += 1
        # Calibrate on every frame until the offset has settled, then sparsely.
        settling = self._calib.n < self.p.calibrate_settle_updates
        every = 1 if settling else self.p.calibrate_every_n_frames
        theta_img = np.zeros(3)
        if key.layers is not None and self._frame_count % every == 0:
            theta = key.layers.residual(img, (peak.du_cells, peak.dv_cells), depth.tz_m, self.p)
            if theta is not None:
                theta_img = theta
                self._calibrate(key, r_rel, attitude, t_att, theta)
        if peak.psr > self.p.psr_refine:
            self._refine(key, img, du, dv, depth.tz_m)
        key.shifts = [*key.shifts[-1:], (t_s, peak.du_cells, peak.dv_cells)]
        # Content moves opposite to the camera (ref. §9): t = -d s.
        s = key.img.res_m
        t_inc = np.array([-peak.du_cells * s, -peak.dv_cells * s, depth.tz_m])
        p_W = key.p_W_m + key.R_W_C @ t_inc
        pose_var = self._pose_variance(peak, s, depth.var_z_m2, key.R_W_C)
        return _Match(p_W, peak, depth, theta_img, pose_var)

    def _reuse(
        self, key: _Key, outcome: _Match | None, cloud: Cloud, t_s: float, r_cur: np.ndarray,
        attitude: AttitudeSource, t_att: float,
    ) -> tuple[_Key, _Match] | None:
        """The match against the current key weakened (PSR < T_r) or failed:
        try the kept keys that look the same way from about the same place,
        and make the best one that matches at least as firmly as a fresh key
        would (PSR >= T_r) the current key again. A frame matched against both
        keys measures their offset: the key positions are refined from all
        offsets measured so far (onboard.keymap)."""
        p_guess = outcome.p_W_m if outcome is not None else self._prev.p_W_m  # type: ignore[union-attr]
        best: tuple[_Key, _Match] | None = None
        for cand in self._map.candidates(
            r_cur, p_guess, key.keyframe_id, self.p.reuse_max_angle_deg, self.p.reuse_max_dist_m,
            self.p.reuse_candidates,
        ):
            cand.shifts = []  # no motion prior against a key not matched for a while: search it all
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

    def _depth_translation(
        self, key: _Key, img: AxonometricImage, du: int, dv: int
    ) -> _DepthFit | None:
        """Eq. 18 with robust gating, plus the residual tilt.

        Delta = D~ - D_key over cells seen in both whose gray agrees (T_c); the
        depth gate is centred on the median rather than the previous t_z, which
        lets fast z motion reject every cell (ref. pitfalls). Under a residual
        rotation theta the differences form a plane,
        Delta = -t_z - theta_x y + theta_y x, fitted in closed form from the
        sums of onboard.kernels.depth_difference_sums (every other row and
        column: a quarter of the cells fixes three parameters just as well).
        """
        s = key.img.res_m
        sums = kern.depth_difference_sums(
            key.depth_ref, key.mask0, key.gray_ref, img.depth_m, img.mask, img.gray, du, dv,
            self.p.gate_gray, self.p.gate_depth_m, s, self.p.min_matched_cells // 16,
        )
        n = float(sums[kern.N])
        if n < self.p.min_matched_cells:
            return None
        sum_d = float(sums[kern.SUM_D])
        z_mean = float(sums[kern.SUM_ZKEY]) / n
        # The authors' sigma_z^2 (ref. §10): scatter of Delta around its mean.
        var_z = max(float(sums[kern.SUM_DD]) / n - (sum_d / n) ** 2, 0.0)
        theta = np.zeros(3)

        def fit(tz: float) -> _DepthFit:
            return _DepthFit(float(tz), theta, z_mean, int(n), var_z)

        if not self.p.depth_tilt_fit:
            return fit(-sum_d / n)
        # Normal equations of Delta ~ a + b (x - mx) + c (y - my), centred on
        # the matched cells so a (their mean) stays well determined even when
        # the overlap is a thin strip far from the axis.
        mx, my = float(sums[kern.SUM_X]) / n, float(sums[kern.SUM_Y]) / n
        sxy = float(sums[kern.SUM_XY]) - n * mx * my
        ata = np.array([
            [float(sums[kern.SUM_XX]) - n * mx * mx, sxy],
            [sxy, float(sums[kern.SUM_YY]) - n * my * my],
        ])
        atb = np.array([float(sums[kern.SUM_DX]) - mx * sum_d, float(sums[kern.SUM_DY]) - my * sum_d])
        try:
            b, c = np.linalg.solve(ata, atb)
        except np.linalg.LinAlgError:
            return fit(-sum_d / n)
        lim = self.p.depth_tilt_max_rad
        theta[0] = np.clip(-c, -lim, lim)
        theta[1] = np.clip(b, -lim, lim)
        # -t_z is the plane's value on the key's optical axis (x = y = 0); the
        # clipped tilt bounds how far a poor fit can move it from the mean.
        tz = -sum_d / n + theta[1] * mx - theta[0] * my
        return fit(tz)

    def _calibrate(
        self,
        key: _Key,
        r_rel: np.ndarray,
        attitude: AttitudeSource,
        t_att: float,
        theta_rad: np.ndarray,
    ) -> None:
        g = self._rate_difference(key, r_rel, attitude, t_att)
        if g is not None:
            self._calib.update(g[:2], theta_rad[:2])

    def _rate_difference(
        self, key: _Key, r_rel: np.ndarray, attitude: AttitudeSource, t_att: float
    ) -> np.ndarray | None:
        """g = omega_key - R_rel omega_cur in key axes (rad/s), see _OffsetCalibration."""
        w_cur = _body_rate(attitude, t_att, self.p.rate_half_window_s)
        w_key = _body_rate(attitude, key.t_s + self._calib.offset_s, self.p.rate_half_window_s)
        if w_cur is None or w_key is None:
            return None
        return w_key - r_rel @ w_cur

    def _refine(self, key: _Key, img: AxonometricImage, du: int, dv: int, tz: float) -> None:
        """Count-weighted moving average of the key images (Eq. 19a/b), as an
        incremental mean: ref += (new - ref) * w_new / (W_k + w_new)."""
        ks, cs = _overlap(self.shape, du, dv)
        w_new = img.mask[cs]
        cnt = key.count[ks]
        cnt += w_new
        gain = w_new / np.maximum(cnt, 1.0)
        key.gray_ref[ks] += (img.gray[cs] - key.gray_ref[ks]) * gain
        # Eq. 19 with I_new - dz: depth moved into the key's axes first.
        key.depth_ref[ks] += (img.depth_m[cs] + tz - key.depth_ref[ks]) * gain

    # ----------------------------------------------------------- key frames
    def _restart(self, t_s: float, cloud: Cloud, r_cur: np.ndarray) -> TrackResult:
        """First key, or a new key after a lost spell placed at the last trusted
        position in the same world frame (the reset counter marks the jump)."""
        p_W = np.zeros(3) if self._last_trusted_p is None else self._last_trusted_p.copy()
        if self._key is not None:
            self._reset_counter += 1
        self._lost = False
        self._prev = _Prev(t_s, cloud, r_cur, None, p_W, np.zeros(3))
        finished = self._new_key_from(self._prev)
        self._last_trusted_p = p_W
        return TrackResult(
            t_s=t_s,
            state=TrackState.TRACKING,
            trusted=True,
            p_W_m=p_W,
            R_W_C=r_cur,
            pose_var=np.array([1e-4, 1e-4, 1e-4, 1e-4, 1e-4, 1e-4]),
            quality=50,
            psr=float("nan"),
            keyframe_id=self._key.keyframe_id,
            new_keyframe=True,
            reset_counter=self._reset_counter,
            lost_reason=None,
            shift_cells=(0.0, 0.0),
            tz_m=0.0,
            res_m=self._key.img.res_m,
            rotation_residual_rad=np.zeros(3),
            attitude_offset_s=self._calib.offset_s,
            matched_cells=0,
            finished_keyframes=tuple(finished),
        )

    def _new_key_from(self, prev: _Prev) -> list[KeyframeCloud]:
        """Project `prev` un-rotated at an adapted resolution and train on it;
        returns the replaced key's cloud for the map."""
        old = self._key
        finished = [] if old is None else [self._key_cloud(old)]
        p = self.p
        res = adaptive_resolution(
            prev.cloud, p.grid_width, p.adaptive_mu, p.max_distance_m, p.len_hist, p.hist_sample,
            self.intr.height / self.intr.width,
        )
        slot = self._store.take()
        img = slot.hold(project(prev.cloud, np.eye(3), self.shape, res, with_colour=True))
        filt = KernelCorrelationFilter(self.shape, p.kernel_sigma, p.lam, p.label_sigma_cells,
                                       slot.spectra)
        filt.train(_whiten(img))
        layers = _RotationResidual.train(img, p) if p.calibrate_time_offset else None
        self._key = _Key(
            keyframe_id=self._next_key_id,
            t_s=prev.t_s,
            p_W_m=np.array(prev.p_W_m, dtype=np.float64),
            R_W_C=prev.R_W_C.copy(),
            img=img,
            filt=filt,
            slot=slot,
            layers=layers,
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

    def _key_cloud(self, key: _Key) -> KeyframeCloud:
        """The key as it is now: copies, since a kept key may be refined and
        moved after the map consumer got it (same id: the newer one wins),
        and its slot is re-used for a later key."""
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
        return TrackResult(
            t_s=t_s,
            state=TrackState.LOST if self._key is not None else TrackState.INITIALIZING,
            trusted=False,
            p_W_m=None,
            R_W_C=None,
            pose_var=np.full(6, np.nan),
            quality=0,
            psr=float("nan"),
            keyframe_id=-1 if self._key is None else self._key.keyframe_id,
            new_keyframe=False,
            reset_counter=self._reset_counter,
            lost_reason=reason,
            shift_cells=(0.0, 0.0),
            tz_m=0.0,
            res_m=0.0 if self._key is None else self._key.img.res_m,
            rotation_residual_rad=np.zeros(3),
            attitude_offset_s=self._calib.offset_s,
            matched_cells=0,
            finished_keyframes=finished,
        )

    def _quality(self, psr: float) -> int:
        span = max(self.p.psr_refine - self.p.psr_lost, 1e-6)
        return int(np.clip(round(100.0 * (psr - self.p.psr_lost) / span), 1, 100))

    def _pose_variance(
        self, peak: Peak, res_m: float, var_z_m2: float, r_W_key: np.ndarray
    ) -> np.ndarray:
        """Position variances in the world frame, attitude variances (ref. §10).

        In key axes: lateral from the response treated as an isotropic 2-D
        Gaussian (s^2 * volume / (2 pi peak)), floored at a tenth of a cell;
        depth from the scatter of the matched depth differences, floored at
        5 mm. The diagonal is carried into the world frame (diag of R S R^T).
        """
        vol = max(peak.response_sum, 0.0)
        var_xy = res_m**2 * max(vol / (2.0 * math.pi * max(peak.value, 1e-9)), 0.01)
        var_key = np.array([var_xy, var_xy, max(var_z_m2, 0.005**2)])
        rot = 2.0 * 4.592449e-6  # authors' fixed attitude variance (rad^2)
        return np.concatenate([(r_W_key * r_W_key) @ var_key, [rot, rot, rot]])


def _whiten(img: AxonometricImage) -> np.ndarray:
    """Zero-mean gray over filled cells, holes at 0: holes then carry no
    pattern of their own (the authors fill them with 0.5, which correlates the
    hole layout of the two images)."""
    return _whiten_masked(img.gray, img.mask)


def _whiten_masked(gray: np.ndarray, mask: np.ndarray) -> np.ndarray:
    n = float(mask.sum())
    mean = float(np.vdot(gray, mask)) / n if n > 0 else 0.0
    out = gray - np.float32(mean)
    out *= mask
    return out


def _overlap(shape: tuple[int, int], du: int, dv: int):
    """Slices (key, current) with current[p + d] aligned to key[p]: a zero-filled,
    non-circular shift (ref. pitfalls: np.roll is wrong here)."""
    h, w = shape
    if abs(du) >= w or abs(dv) >= h:
        return None, None
    ky = slice(max(0, -dv), min(h, h - dv))
    kx = slice(max(0, -du), min(w, w - du))
    cy = slice(ky.start + dv, ky.stop + dv)
    cx = slice(kx.start + du, kx.stop + du)
    return (ky, kx), (cy, cx)


def _body_rate(attitude: AttitudeSource, t_s: float, half_s: float) -> np.ndarray | None:
    """Angular rate in the camera frame from two attitude look-ups (rad/s)."""
    r0 = attitude.rotation_at(t_s - half_s)
    r1 = attitude.rotation_at(t_s + half_s)
    if r0 is None or r1 is None:
        return None
    return so3_log(r0.T @ r1) / (2.0 * half_s)


