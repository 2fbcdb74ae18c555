"""The final trajectory of a run with a back end, as ORB-SLAM2 saves it for
evaluation (System::SaveTrajectoryTUM): each tracked frame's pose is kept
relative to its key frame as that key frame was at the time; at the end the
frames are placed on their key frames' final poses, so what loop closing
and bundle adjustment learnt later reaches the frames before it too.

The online trajectory (trajectory.tum, ate_rmse_m) is what was sent to the
flight controller; this one (ate_final_rmse_m) scores the map.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from onboard.core.messages import TrackResult
from onboard.core.se3 import inverse, make_pose
from onboard.core.trajectory import Trajectory

PoseOf = Callable[[int], "np.ndarray | None"]  # key frame id -> its T_cw now, None: unknown


class KeyframeAnchors:
    def __init__(self, pose_of: PoseOf):
        self._pose_of = pose_of
        self._rel: list[tuple[int, np.ndarray] | None] = []  # per trusted frame

    def add(self, result: TrackResult) -> None:
        """A trusted frame: its pose in its key frame's axes, as they are now."""
        ref = result.reference_keyframe_id if result.reference_keyframe_id >= 0 else (
            result.keyframe_id)
        T_cw_ref = self._pose_of(ref) if ref >= 0 else None
        if T_cw_ref is None or result.R_W_C is None or result.p_W_m is None:
            self._rel.append(None)
            return
        self._rel.append((ref, T_cw_ref @ make_pose(result.R_W_C, result.p_W_m)))

    def final(self, online: Trajectory) -> Trajectory:
        """The online trajectory with every anchored frame on its key frame's
        final pose (frames whose key frame is gone keep their online pose)."""
        p, q = online.p_xyz_m.copy(), online.q_xyzw.copy()
        for n, anchor in enumerate(self._rel[: len(online)]):
            T_cw_ref = None if anchor is None else self._pose_of(anchor[0])
            if T_cw_ref is None:
                continue
            T_wc = inverse(T_cw_ref) @ anchor[1]
            p[n] = T_wc[:3, 3]
            q[n] = Rotation.from_matrix(T_wc[:3, :3]).as_quat()
        return Trajectory(online.t_s, p, q)
