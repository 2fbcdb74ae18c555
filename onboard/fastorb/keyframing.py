"""FastORB's key frames and new landmarks (step 7 of tracker.py), and the
work a frame's pose does not need, done after the pose went out.

A key frame's pose comes from the local map (map_tracking.local_map); what
follows it serves the next frames only: pairing the keypoints with the
tracked points, new landmarks from depth, the key frame's entry in the
local map and the back end's queues, its dense cloud for the map output,
and (below redetect_min_inliers) new keypoints. `track()` queues that work
and `finish_frame()` runs it, once the caller has sent the pose (as NI-SLAM
does with its new key, onboard/nislam/deferred.py). Nothing else changes:
the queue runs before anything reads what it writes (the next `track()`,
`backend_step()`, `keyframe_pose()` and `finish()` run it first), so the
poses are those of the work done in place.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from onboard.core.messages import KeyframeCloud, RgbdFrame
from onboard.fastorb.features import Detector, Outcome, Tracked
from onboard.fastorb.landmark_rate import (
    Unsettled,
    central_rate,
    reposed_moves,
    settle,
    unsettled,
)
from onboard.fastorb.local_map import (
    CloudGrid,
    Keyframe,
    LocalMap,
    cloud_grid,
    grid_cloud,
    sample_depth,
)
from onboard.fastorb.loop import LoopClosing
from onboard.fastorb.mapping import LocalMapping
from onboard.fastorb.params import FastOrbParams
from onboard.fastorb.pose import disparity
from onboard.fastorb.shutter import points_at_mid


class KeyframeMaking:
    """Key-frame and landmark making of FastOrbTracker (a mixin: the
    tracker owns the state named below)."""

    p: FastOrbParams
    K: np.ndarray
    _size: tuple[int, int]
    _detector: Detector
    _map: LocalMap
    mapping: LocalMapping | None
    loops: LoopClosing
    _xi: np.ndarray
    _tracked: Tracked
    _unfinished: Keyframe | None
    _unfinished_grid: CloudGrid | None
    _deferred: list[Callable[[], None]]
    _keyframe_queued: bool
    _next_keyframe_id: int
    _next_landmark_id: int
    _frames_since_keyframe: int
    _keyframe_inliers: int
    _history: deque[tuple[float, np.ndarray]]
    _t_motion: float
    _unsettled: list[Unsettled]

    def finish_frame(self) -> None:
        """The last frame's work for the next frames (a new key frame, new
        keypoints), for after its pose went out; a no-op when none is queued."""
        while self._deferred:
            jobs, self._deferred = self._deferred, []
            for job in jobs:
                job()

    def _keyframe_after_pose(self, frame: RgbdFrame, gray: np.ndarray, outcome: Outcome
                             ) -> tuple[KeyframeCloud, ...]:
        """A key frame from this posed frame, made by `finish_frame()`: the
        previous key frame's cloud now (it goes out with this frame's result,
        as before), the rest queued."""
        finished = self._take_cloud()
        self._keyframe_queued = True

        def job() -> None:
            self._keyframe_queued = False
            self._add_keyframe(frame, gray, outcome, self._poses_around(outcome.T_cw))
            self._tracked = outcome.tracked

        self._deferred.append(job)
        return () if finished is None else (finished,)

    def _replenish_after_pose(self, frame: RgbdFrame, gray: np.ndarray, outcome: Outcome) -> None:
        """`_replenish`, queued for `finish_frame()`."""
        def job() -> None:
            outcome.tracked = self._replenish(frame, gray, outcome.T_cw, outcome.tracked,
                                              self._poses_around(outcome.T_cw))
            self._tracked = outcome.tracked

        self._deferred.append(job)

    def _newest_keyframe_id(self) -> int:
        """The newest key frame's id (a queued one's included); -1: none."""
        if self._keyframe_queued:
            return self._next_keyframe_id
        kf = self._map.newest
        return -1 if kf is None else kf.keyframe_id

    def _replenish(
        self, frame: RgbdFrame, gray: np.ndarray, T_cw: np.ndarray, tracked: Tracked,
        around: tuple[np.ndarray, float, float] | None = None,
    ) -> Tracked:
        """Fewer than redetect_min_inliers: ORB detection only (no descriptors)
        where no tracked point is, new landmarks from depth."""
        feats = self._detector.detect(gray, with_descriptors=False, avoid=tracked.uv)
        new, _ = self._landmarks(frame, T_cw, feats.uv[self._detector.free(tracked.uv, feats.uv)],
                                 around)
        room = max(self.p.orb_features - len(tracked), 0)
        return tracked.extended(new.subset(slice(0, room)))

    def _landmarks(
        self, frame: RgbdFrame, T_cw: np.ndarray, uv: np.ndarray,
        around: tuple[np.ndarray, float, float] | None = None,
        inliers: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> tuple[Tracked, np.ndarray]:
        """New landmarks (fresh ids) for those pixels `uv` that have usable
        depth, and which those were (bool (N,)). With the pose before this
        one, `around` = (T_prev, t_prev, t_now), they are settled with the
        poses' rate once the next frame is posed (landmark_rate.py); with the
        frame's `inliers` (raw pixels, landmarks, disparities), from its pose
        solved again with that rate (reposed_moves)."""
        z = sample_depth(frame.depth_m, uv, self.p.min_depth_m, self.p.max_depth_m,
                         self.p.depth_edge_rel)
        ok = z > 0
        n = int(ok.sum())
        ids = np.arange(self._next_landmark_id, self._next_landmark_id + n, dtype=np.int64)
        self._next_landmark_id += n
        p_C = points_at_mid(uv[ok], z[ok], self.K, self._xi, self.p.rolling_shutter_readout_s,
                            self._size[1])
        xyz = (p_C - T_cw[:3, 3]) @ T_cw[:3, :3]  # R^T (p_C - t), row-wise
        if around is not None and n:
            T_prev, t_prev, t_now = around
            u = unsettled(
                ids, uv[ok], z[ok], self.K, self._xi[:3], self.p.rolling_shutter_readout_s,
                self._size[1], T_cw, t_now, T_prev, t_prev)
            if inliers is not None:
                u = replace(u, inliers=(*inliers, self._xi[3:].copy()))
            self._unsettled.append(u)
        return Tracked(uv[ok].astype(np.float32), xyz, ids), ok

    # ------------------------------------------- landmarks settled (landmark_rate.py)
    def _poses_around(self, T_cw: np.ndarray) -> tuple[np.ndarray, float, float] | None:
        """(T_prev, t_prev, t_now) when the posed frame T_cw (the newest in
        the motion model) has a pose before it and its landmarks are to be
        settled with the poses' rate (a rolling shutter); else None."""
        if (not self.p.rolling_shutter_settle_landmarks or not self.p.rolling_shutter_readout_s
                or len(self._history) < 2 or self._history[-1][1] is not T_cw):
            return None
        (t_prev, T_prev), (t_now, _) = self._history[-2], self._history[-1]
        return T_prev, t_prev, t_now

    def _settle_after_pose(self, outcome: Outcome) -> None:
        """The last posed frame's new landmarks, moved to where the central
        difference of the poses on both sides of it (the previous one and
        this frame's `outcome.T_cw`) puts them; queued for `finish_frame()`
        ahead of this frame's own key-frame work, which may take them over.
        Landmarks of a frame that is not this one's direct predecessor in the
        motion model (a coasted frame between, a loss, a loop correction that
        moved the poses) stay as they were made."""
        pending, self._unsettled = self._unsettled, []
        if not pending or not self._history:
            return
        last = self._history[-1][1]
        pending = [u for u in pending if u.T_cw is last]
        if not pending:
            return
        T_next, t_next = outcome.T_cw, self._t_motion

        def job() -> None:
            ids, moves = [], []
            for u in pending:
                ids.append(u.ids)
                w = central_rate(u, T_next, t_next)
                moves.append(settle(u, w) if u.inliers is None else reposed_moves(
                    u, w, self.K, self.p.rolling_shutter_readout_s, self._size[1],
                    self.p.pnp_huber_px, self.p.rgbd_bf_px))
            self._move_landmarks(np.concatenate(ids), np.concatenate(moves), outcome)

        self._deferred.insert(0, job)

    def _move_landmarks(self, ids: np.ndarray, moves: np.ndarray, outcome: Outcome) -> None:
        """Landmarks `ids` moved by `moves` (world) in the tracked set and in
        the newest key frames (the one that made them, if any)."""
        order = np.argsort(ids)
        ids, moves = ids[order], moves[order]

        def moved(their_ids: np.ndarray, xyz_W: np.ndarray) -> np.ndarray | None:
            """A copy of `xyz_W` with the moved landmarks moved; None if none is there."""
            pos = np.minimum(np.searchsorted(ids, their_ids), len(ids) - 1)
            hit = ids[pos] == their_ids
            if not hit.any():
                return None
            xyz = xyz_W.copy()
            xyz[hit] += moves[pos[hit]]
            return xyz

        trk = outcome.tracked
        xyz = moved(trk.ids, trk.xyz_W)
        if xyz is not None:
            trk.xyz_W = xyz
        changed = False
        for kf in self._map.newest_first(2):
            xyz = moved(kf.ids, kf.xyz_W)
            if xyz is not None:
                kf.xyz_W = xyz  # replaced, never written in place (loop.py keeps references)
                self.loops.points_moved(kf)
                changed = True
        if changed:
            self._map.changed()

    # ------------------------------------------------------------ key frames
    def _keyframe_due(self, n_inliers: int) -> bool:
        """Sec. III: a key frame once over keyframe_max_frames frames have passed
        since the last, or tracking has dropped below keyframe_inlier_ratio of
        the last key's inliers (ORB-SLAM2's rule; the paper's third trigger,
        an idle local-mapping thread, has no counterpart without a back end);
        never with fewer than keyframe_min_inliers tracked inliers."""
        if n_inliers < self.p.keyframe_min_inliers:
            return False
        return (self._frames_since_keyframe >= self.p.keyframe_max_frames
                or n_inliers < self.p.keyframe_inlier_ratio * self._keyframe_inliers)

    def _make_keyframe(
        self, frame: RgbdFrame, gray: np.ndarray, outcome: Outcome
    ) -> tuple[KeyframeCloud, ...]:
        """The posed frame becomes a key frame now (a new map, re-localisation);
        returns the previous key frame's cloud, if any."""
        finished = self._take_cloud()
        self._add_keyframe(frame, gray, outcome)
        return () if finished is None else (finished,)

    def _add_keyframe(self, frame: RgbdFrame, gray: np.ndarray, outcome: Outcome,
                      around: tuple[np.ndarray, float, float] | None = None) -> None:
        """The posed frame with descriptors becomes a key frame (step 7). A
        keypoint on a tracked point takes its landmark, the others get new
        ones from depth; those away from tracked points join the tracked set."""
        feats = outcome.features
        assert feats is not None and feats.desc is not None
        tracked = outcome.tracked
        on = self._detector.pair_with(tracked.uv, feats.uv, 1.5)
        inliers = None
        if around is not None and self.p.rolling_shutter_repose:  # the pose's own points
            zi = sample_depth(frame.depth_m, tracked.uv, self.p.min_depth_m,
                              self.p.rgbd_max_depth_m, self.p.depth_edge_rel)
            inliers = (tracked.uv.astype(np.float64), tracked.xyz_W.copy(),
                       disparity(zi, len(zi), self.p.rgbd_bf_px))
        fresh, has_depth = self._landmarks(frame, outcome.T_cw, feats.uv[on < 0], around,
                                           inliers)
        kf_idx = np.concatenate([np.flatnonzero(on >= 0), np.flatnonzero(on < 0)[has_depth]])
        kf_pts = tracked.subset(on[on >= 0]).extended(fresh)
        free = self._detector.free(tracked.uv, fresh.uv)
        room = max(self.p.orb_features - len(tracked), 0)
        outcome.tracked = tracked.extended(fresh.subset(np.flatnonzero(free)[:room]))
        z = sample_depth(frame.depth_m, kf_pts.uv, self.p.min_depth_m, self.p.max_depth_m,
                         self.p.depth_edge_rel)
        kf = Keyframe(self._next_keyframe_id, frame.t_s, outcome.T_cw.copy(), gray,
                      kf_pts.uv.astype(np.float64), feats.desc[kf_idx], kf_pts.xyz_W, kf_pts.ids,
                      frame.bgr, frame.depth_m, z)
        self._next_keyframe_id += 1
        self._map.add(kf)
        if self.mapping is not None:
            self.mapping.on_keyframe(kf)
        self.loops.on_keyframe(kf)
        self._unfinished = kf
        # Its cloud's grid now (after the pose), the pose it is handed out at
        # when the next key frame takes it (_take_cloud): a back-end slice may
        # move the key frame before then.
        self._unfinished_grid = (cloud_grid(kf, self.K, self.p.map_cloud_stride,
                                            self.p.min_depth_m, self.p.max_depth_m)
                                 if self.p.map_cloud_stride > 0 else None)
        self._frames_since_keyframe = 0
        # The 65 % rule's reference is what the key frame hands on to tracking
        # (its inliers and the points it added), not its inliers alone: after
        # a key frame that added 480 points to 150 inliers, a reference of
        # 150 waited for the 630 to drop below 98, under keyframe_min_inliers,
        # so the next key frame never came (aggressive, 60 deg/s).
        self._keyframe_inliers = len(outcome.tracked)

    def _take_cloud(self) -> KeyframeCloud | None:
        kf, self._unfinished = self._unfinished, None
        grid, self._unfinished_grid = self._unfinished_grid, None
        if kf is None or grid is None:
            return None
        return grid_cloud(kf, grid)
