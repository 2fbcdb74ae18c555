"""What FastORB tracks between frames: keypoints, the points followed from frame
to frame with their landmarks, and a posed frame's outcome.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from onboard.core.messages import KeyframeCloud, TrackResult, TrackState
from onboard.core.se3 import camera_in_world
from onboard.fastorb.params import FastOrbParams
from onboard.fastorb.pose import PnpResult, world_pose_variance


@dataclass
class Features:
    """ORB keypoints of the current frame; `desc` only when computed."""

    uv: np.ndarray  # (N, 2) float64
    desc: np.ndarray | None  # (N, 32) uint8


@dataclass
class Tracked:
    """Points followed from frame to frame: pixel in the last frame, and the
    landmark each observes (id and world position, fixed at its creation)."""

    uv: np.ndarray  # (N, 2) float32
    xyz_W: np.ndarray  # (N, 3)
    ids: np.ndarray  # (N,) int64

    @classmethod
    def empty(cls) -> "Tracked":
        return cls(np.zeros((0, 2), np.float32), np.zeros((0, 3)), np.zeros(0, np.int64))

    def __len__(self) -> int:
        return len(self.uv)

    def subset(self, sel: np.ndarray) -> "Tracked":
        return Tracked(self.uv[sel], self.xyz_W[sel], self.ids[sel])

    @classmethod
    def joined(cls, parts: list["Tracked"]) -> "Tracked":
        if not parts:
            return cls.empty()
        return cls(np.concatenate([p.uv for p in parts]).astype(np.float32, copy=False),
                   np.concatenate([p.xyz_W for p in parts]),
                   np.concatenate([p.ids for p in parts]))

    def extended(self, other: "Tracked") -> "Tracked":
        return Tracked(
            np.concatenate([self.uv, other.uv.astype(np.float32)]),
            np.concatenate([self.xyz_W, other.xyz_W]),
            np.concatenate([self.ids, other.ids]),
        )


@dataclass
class Outcome:
    """A posed frame: pose, the tracked set for the next frame (PnP inliers
    and new points), the PnP fit, and the frame's keypoints if detected."""

    T_cw: np.ndarray
    tracked: Tracked
    pnp: PnpResult
    features: Features | None

    @property
    def inliers(self) -> int:
        return int(self.pnp.inliers.sum())


class Detector:
    """ORB keypoints of a frame (detection only, or with descriptors for key
    frames), kept about `min_point_distance_px` away from points already
    followed, so new keypoints spread over the image."""

    def __init__(self, p: FastOrbParams, size: tuple[int, int]) -> None:
        self._orb = cv2.ORB_create(
            nfeatures=p.orb_features, scaleFactor=p.orb_scale_factor, nlevels=p.orb_levels,
            fastThreshold=p.orb_fast_threshold,
        )
        self._min_distance_px = p.min_point_distance_px
        self._size = size  # (width, height)

    def detect(
        self, gray: np.ndarray, with_descriptors: bool, avoid: np.ndarray | None = None
    ) -> Features:
        """ORB keypoints (ORB.detect only, or detectAndCompute for key frames),
        optionally masked away from the pixels `avoid`."""
        mask = None if avoid is None or len(avoid) == 0 else self._free_mask(avoid)
        if with_descriptors:
            kps, desc = self._orb.detectAndCompute(gray, mask)
            if desc is None:
                desc = np.zeros((0, 32), np.uint8)
        else:
            kps, desc = self._orb.detect(gray, mask), None
        uv = cv2.KeyPoint_convert(kps).astype(np.float64).reshape(-1, 2) if kps else np.zeros((0, 2))
        return Features(uv, desc)

    def _occupancy(self, uv: np.ndarray) -> tuple[np.ndarray, int]:
        """Cells of min_point_distance_px with a point in them or a neighbour."""
        cell = max(int(self._min_distance_px), 1)
        w, h = self._size
        occ = np.zeros((h // cell + 1, w // cell + 1), np.uint8)
        if len(uv):
            c = np.clip((uv // cell).astype(np.int64), 0, [occ.shape[1] - 1, occ.shape[0] - 1])
            occ[c[:, 1], c[:, 0]] = 1
            occ = cv2.dilate(occ, np.ones((3, 3), np.uint8))
        return occ, cell

    @staticmethod
    def pair_with(taken: np.ndarray, uv: np.ndarray, radius_px: float) -> np.ndarray:
        """For each of `uv`, the index of the nearest of `taken` within
        `radius_px`, or -1."""
        if len(taken) == 0 or len(uv) == 0:
            return np.full(len(uv), -1, np.int64)
        dist, j = cKDTree(taken).query(uv, distance_upper_bound=radius_px)
        return np.where(np.isfinite(dist), j, -1).astype(np.int64)

    def free(self, taken: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Which of `uv` lie away (about min_point_distance_px) from `taken`."""
        occ, cell = self._occupancy(taken)
        c = np.clip((uv // cell).astype(np.int64), 0, [occ.shape[1] - 1, occ.shape[0] - 1])
        return occ[c[:, 1], c[:, 0]] == 0

    def _free_mask(self, taken: np.ndarray) -> np.ndarray:
        occ, cell = self._occupancy(taken)
        w, h = self._size
        full = np.repeat(np.repeat(occ, cell, axis=0), cell, axis=1)[:h, :w]
        return np.where(full > 0, 0, 255).astype(np.uint8)


def outcome_result(
    t_s: float,
    state: TrackState,
    outcome: Outcome | None,
    reason: str | None,
    new_key: bool,
    finished: tuple[KeyframeCloud, ...],
    keyframe_id: int,
    reset_counter: int,
    full_quality_inliers: int,
    loop_corrections: int = 0,
    moved_keyframes: tuple[tuple[int, np.ndarray, np.ndarray], ...] = (),
) -> TrackResult:
    """The tracker's result for a frame: a pose (trusted) with `outcome`, else none."""
    if outcome is None:
        p_W = R_W_C = None
        pose_var, quality, n_in = np.full(6, np.nan), 0, 0
    else:
        p_W, R_W_C = camera_in_world(outcome.T_cw)
        pose_var = world_pose_variance(outcome.T_cw, outcome.pnp.cov)
        n_in = outcome.inliers
        quality = pose_quality(n_in, outcome.pnp.rms_px, full_quality_inliers)
    return TrackResult(
        t_s=t_s,
        state=state,
        trusted=outcome is not None,
        p_W_m=p_W,
        R_W_C=R_W_C,
        pose_var=pose_var,
        quality=quality,
        psr=float("nan"),  # no correlation peak in this tracker
        keyframe_id=keyframe_id,
        new_keyframe=new_key,
        reset_counter=reset_counter,
        lost_reason=reason,
        shift_cells=(0.0, 0.0),
        tz_m=0.0,
        res_m=0.0,
        rotation_residual_rad=np.zeros(3),
        attitude_offset_s=0.0,
        matched_cells=n_in,  # PnP inliers
        finished_keyframes=finished,
        loop_corrections=loop_corrections,
        moved_keyframes=moved_keyframes,
    )


def pose_quality(n_inliers: int, rms_px: float, full_quality_inliers: int) -> int:
    """100 at `full_quality_inliers` inliers (redetect_min_inliers) and
    sub-pixel residuals; falls with fewer inliers and with the reprojection
    RMS beyond 1 px."""
    share = min(n_inliers / max(full_quality_inliers, 1), 1.0)
    return int(np.clip(round(100.0 * share / max(rms_px, 1.0)), 1, 100))
