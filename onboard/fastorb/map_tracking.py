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
from onboard.fastorb.pose import PnpResult, PnpSettings, restricted, solve_pnp


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

    def solve(self, xyz_W: np.ndarray, uv: np.ndarray, depth_m: np.ndarray) -> PnpResult | None:
        """PnP + RANSAC, then refinement against the landmarks
        with this frame's depth at the tracked pixels (closer than
        rgbd_max_depth_m) as disparity residuals."""
        z = sample_depth(depth_m, uv, self.p.min_depth_m, self.p.rgbd_max_depth_m,
                         self.p.depth_edge_rel) if len(uv) else np.zeros(0)
        return solve_pnp(xyz_W, uv, self.K, self.pnp, self.p.min_inliers, z)

    def local_map(
        self,
        frame: RgbdFrame,
        gray: np.ndarray,
        guess: np.ndarray,
        kept: Tracked,
        feats: Features | None = None,
    ) -> Outcome | None:
        """Track against the local map: ORB with descriptors on this frame,
        matched to the landmarks of the key frames nearest to the pose `guess`
        (projected with it); PnP on those and the still-tracked points. A
        tracked point that meets an older landmark takes it over, so drift
        does not outlive the return to a mapped view."""
        if feats is None:
            feats = self.detector.detect(gray, with_descriptors=True)
        found = self.match_map(feats, guess)
        near = self.detector.pair_with(kept.uv, found.uv, 2.0)  # kept index per found point, -1: none
        older = near >= 0
        older[older] = found.ids[older] < kept.ids[near[older]]
        kept = Tracked(kept.uv, kept.xyz_W.copy(), kept.ids.copy())
        kept.xyz_W[near[older]] = found.xyz_W[older]
        kept.ids[near[older]] = found.ids[older]
        new = (near < 0) & ~np.isin(found.ids, kept.ids)
        both = kept.extended(found.subset(new))
        pnp = self.solve(both.xyz_W, both.uv, frame.depth_m)
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

    def match_map(self, feats: Features, guess: np.ndarray) -> Tracked:
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
        return Tracked(feats.uv[kp_i].astype(np.float32), mp.xyz_W[map_i], mp.ids[map_i])
