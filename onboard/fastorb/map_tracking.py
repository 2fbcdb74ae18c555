"""FastORB's tracking against the map (Fu et al., TIP 2022, Sec. IV; steps 5
and 6 of tracker.py): the pose from landmark/pixel pairs with this frame's
depth, landmarks of nearby key frames followed by LK without descriptors,
and the local map matched by descriptors when a key frame is made or
tracking thins out. Pure: the tracker owns the state, this owns the method."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from onboard.core.messages import RgbdFrame
from onboard.fastorb.features import Detector, Features, Outcome, Tracked
from onboard.fastorb.local_map import LocalMap, sample_depth
from onboard.fastorb.matching import LkSettings, match_by_projection, track_lk
from onboard.fastorb.motion import project
from onboard.fastorb.params import FastOrbParams
from onboard.fastorb.pose import PnpResult, PnpSettings, disparity, restricted, solve_pnp
from onboard.fastorb.shutter import pixels_at_mid, refine_with_rate


@dataclass
class MapTracking:
    """The map-facing half of the front end, for one camera."""

    p: FastOrbParams
    K: np.ndarray
    size: tuple[int, int]  # (width, height) px
    detector: Detector
    map: LocalMap
    lk: LkSettings
    pnp: PnpSettings
    rate: np.ndarray | None = None  # body rate [rad/s] the last solve measured (rolling shutter)

    def solve(self, xyz_W: np.ndarray, uv: np.ndarray, depth_m: np.ndarray,
              prior: np.ndarray | None = None, xi: np.ndarray | None = None) -> PnpResult | None:
        """PnP + RANSAC (or the predicted pose `prior` where RANSAC's re-fit
        failed, pose._start), then refinement against the landmarks with this frame's
        depth at the tracked pixels (closer than rgbd_max_depth_m) as
        disparity residuals. With a rolling shutter and the camera's twist
        `xi` (per second), the pixels are first brought to the middle row's
        instant (shutter.py), at the depth the landmark has under `prior`."""
        z = sample_depth(depth_m, uv, self.p.min_depth_m, self.p.rgbd_max_depth_m,
                         self.p.depth_edge_rel) if len(uv) else np.zeros(0)
        readout = self.p.rolling_shutter_readout_s
        self.rate = None
        if not (readout and xi is not None and prior is not None and len(uv)):
            return solve_pnp(xyz_W, uv, self.K, self.pnp, self.p.min_inliers, z, prior)
        depth = project(self.K, prior, xyz_W)[1]
        fit = solve_pnp(xyz_W, pixels_at_mid(uv, depth, self.K, xi, readout, self.size[1]),
                        self.K, self.pnp, self.p.min_inliers, z, prior)
        if fit is None:
            return None
        # The rate the rows' shear shows (shutter.refine_with_rate), then the
        # pose again on pixels brought to the middle row with it: the motion
        # model's rate is the last interval's, half a frame old and as noisy
        # as two poses (tum_fr1_rpy: lag-1 RPE 9.4 -> 12.1 mm with it alone).
        inl = fit.inliers
        disp = disparity(z, len(z), self.pnp.bf_px)
        T, omega = refine_with_rate(fit.T_cw, xyz_W[inl], uv[inl], disp[inl], self.K,
                                    self.pnp.bf_px, self.pnp.huber_px, readout, self.size[1],
                                    xi, self.p.rolling_shutter_rate_sd)
        xi_fit = np.concatenate([omega, xi[3:]])
        again = solve_pnp(xyz_W, pixels_at_mid(uv, project(self.K, T, xyz_W)[1], self.K, xi_fit,
                                               readout, self.size[1]),
                          self.K, self.pnp, self.p.min_inliers, z, T)
        if again is None or again.inliers.sum() < fit.inliers.sum():
            self.rate = xi[:3].copy()  # a blurred frame's shear misleads: keep the first fit
            return fit
        self.rate = omega
        return again

    def local_map(
        self,
        frame: RgbdFrame,
        gray: np.ndarray,
        guess: np.ndarray,
        kept: Tracked,
        feats: Features | None = None,
        xi: np.ndarray | None = None,
    ) -> Outcome | None:
        """Track against the local map: ORB with descriptors on this frame,
        matched to the landmarks of the key frames nearest to the pose `guess`
        (projected with it); PnP on those and the still-tracked points. A
        tracked point that meets an older landmark takes it over, so drift
        does not outlive the return to a mapped view."""
        if feats is None:
            feats = self.detector.detect(gray, with_descriptors=True)
        found = self.match_map(feats, guess, gray)
        near = self.detector.pair_with(kept.uv, found.uv, 2.0)  # kept index per found point, -1: none
        older = near >= 0
        older[older] = found.ids[older] < kept.ids[near[older]]
        kept = Tracked(kept.uv, kept.xyz_W.copy(), kept.ids.copy())
        kept.xyz_W[near[older]] = found.xyz_W[older]
        kept.ids[near[older]] = found.ids[older]
        new = (near < 0) & ~np.isin(found.ids, kept.ids)
        both = kept.extended(found.subset(new))
        pnp = self.solve(both.xyz_W, both.uv, frame.depth_m, guess, xi)
        if pnp is None:
            return None
        return Outcome(pnp.T_cw, both.subset(pnp.inliers), restricted(pnp), feats)

    def map_points(self, gray: np.ndarray, prior: np.ndarray, moved: Tracked) -> Tracked:
        """Descriptor-free local-map tracking: landmarks of the key frames
        nearest to the predicted pose that project into this frame away from
        the followed points, followed by LK from their key frame's image,
        starting at the projection. Landmarks that left the view and came
        back are re-acquired with their old position, which holds drift back."""
        mp = self.map.points_near(prior)
        rows = np.flatnonzero((mp.kf < self.p.map_track_keyframes) & ~mp.has(moved.ids))
        uv, z = project(self.K, prior, mp.xyz_W[rows])
        w, h = self.size
        m = 8  # keep the LK window and its pyramid footprint inside the image
        view = ((z > self.p.min_depth_m) & (uv[:, 0] >= m) & (uv[:, 0] < w - m)
                & (uv[:, 1] >= m) & (uv[:, 1] < h - m))
        sel = np.flatnonzero(view)
        sel = sel[self.detector.free(moved.uv, uv[sel])][: self.p.map_track_max]
        kf = mp.kf[rows[sel]]
        parts = []
        for slot in np.unique(kf):
            g = sel[kf == slot]
            at, ok = track_lk(mp.keyframes[slot].gray, gray, mp.uv[rows[g]], uv[g], self.lk)
            ok &= np.sum((at - uv[g]) ** 2, axis=1) <= self.p.map_track_radius_px**2
            parts.append(Tracked(at[ok], mp.xyz_W[rows[g[ok]]], mp.ids[rows[g[ok]]]))
        return Tracked.joined(parts)

    def match_map(self, feats: Features, guess: np.ndarray, gray: np.ndarray) -> Tracked:
        """Keypoints matched to local-map landmarks by projection and descriptor."""
        mp = self.map.points_near(guess)
        uv_map, z_map = project(self.K, guess, mp.xyz_W)
        w, h = self.size
        view = np.flatnonzero((z_map > self.p.min_depth_m) & (uv_map[:, 0] >= 0)
                              & (uv_map[:, 0] < w) & (uv_map[:, 1] >= 0) & (uv_map[:, 1] < h))
        kp_i, map_i = match_by_projection(
            feats.desc, feats.uv, mp.desc[view], uv_map[view], self.p.match_radius_px,
            self.p.match_max_hamming,
        )
        map_i = view[map_i]
        uv = feats.uv[kp_i].astype(np.float32)
        if self.p.map_match_lk_px > 0:
            uv = self._lk_refined(gray, mp, map_i, uv)
        return Tracked(uv, mp.xyz_W[map_i], mp.ids[map_i])

    def _lk_refined(self, gray: np.ndarray, mp, rows: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """The matched keypoints' pixels moved to where LK from each
        landmark's key frame puts the landmark, if within map_match_lk_px.
        An ORB keypoint of octave k sits within about 1.2^k / 2 px of its
        corner (ORB-SLAM2 weighs it by 1 / 1.2^(2k)); a landmark found again
        by it keeps that offset in every frame LK then follows it through,
        while the landmark's position belongs to the pixel of the key frame
        that made it. LK from that key frame's image lands on the same
        texture to a tenth of a pixel (where the view has not turned or
        scaled too far; elsewhere the keypoint stays)."""
        out = uv.copy()
        kf = mp.kf[rows]
        for slot in np.unique(kf):
            g = np.flatnonzero(kf == slot)
            at, ok = track_lk(mp.keyframes[slot].gray, gray, mp.uv[rows[g]], uv[g], self.lk)
            ok &= np.sum((at - uv[g]) ** 2, axis=1) <= self.p.map_match_lk_px**2
            out[g[ok]] = at[ok]
        return out
