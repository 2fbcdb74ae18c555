"""Small typed messages shared by sources, trackers and outputs.

Conventions (see docs/frames.md): camera optical frame C (x right, y down,
z forward); transforms named R_<to>_<from>; quaternions carry their order in
the name (`q_xyzw` as TUM/scipy, `q_wxyz` as MAVLink).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class RgbdFrame:
    """One colour + registered depth pair, already undistorted.

    `bgr`: (H, W, 3) uint8 in OpenCV channel order; `depth_m`: (H, W) float32
    metres with 0 = no measurement; `t_s`: capture time on the source's clock
    (of the colour image when `depth_t_s` gives the depth's own).
    """

    t_s: float
    bgr: np.ndarray
    depth_m: np.ndarray
    # When the depth image was captured, if not with the colour (a Kinect
    # pairs them up to 20 ms apart); None = at `t_s`.
    depth_t_s: float | None = None


class AttitudeSource(Protocol):
    """Where a tracker asks for the camera's orientation at a capture time."""

    def rotation_at(self, t_s: float) -> np.ndarray | None:
        """R_W_C (3x3, camera optical to attitude world) at `t_s`, or None when
        no trustworthy attitude covers that time."""
        ...


class TrackState(enum.Enum):
    INITIALIZING = "initializing"
    TRACKING = "tracking"
    LOST = "lost"


@dataclass(frozen=True)
class KeyframeCloud:
    """A finished (refined) key: its images and pose. `points()` turns it into
    a coloured cloud in the world frame; it is lazy so the tracking loop only
    hands over references and the map consumer pays for the conversion."""

    keyframe_id: int
    t_s: float
    p_W_m: np.ndarray  # key camera position (3,)
    R_W_C: np.ndarray  # key camera orientation (3, 3)
    res_m: float
    depth_m: np.ndarray  # refined axonometric depth (H, W), 0 = empty
    gray: np.ndarray  # refined gray (H, W) in [0, 1]
    bgr: np.ndarray  # the key's own colour (H, W, 3) uint8, 0 where it saw nothing

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """(xyz_W_m (N,3) float32, rgb (N,3) uint8) of the filled cells: cell
        centre and refined depth in key axes, then the key pose (ref. §11).
        Cells filled only by refinement take their refined gray as colour."""
        h, w = self.depth_m.shape
        vv, uu = np.nonzero(self.depth_m > 0)
        s = self.res_m
        pts = np.stack(
            [(uu - w // 2 + 0.5) * s, (vv - h // 2 + 0.5) * s, self.depth_m[vv, uu]], axis=1
        )
        xyz = (pts @ self.R_W_C.T + self.p_W_m).astype(np.float32)
        rgb = self.bgr[vv, uu, ::-1].copy()
        no_colour = ~rgb.any(axis=1)
        rgb[no_colour] = np.clip(self.gray[vv, uu][no_colour] * 255.0 + 0.5, 0, 255)[:, None]
        return xyz, rgb.astype(np.uint8)


@dataclass(frozen=True)
class TrackResult:
    """What `track()` tells about one frame.

    `p_W_m` / `R_W_C` are None unless `trusted`: a frame the tracker could not
    match carries no pose at all, so nothing downstream can send it.
    """

    t_s: float
    state: TrackState
    trusted: bool
    p_W_m: np.ndarray | None
    R_W_C: np.ndarray | None
    pose_var: np.ndarray  # (6,) variances x, y, z [m^2], roll, pitch, yaw [rad^2]
    quality: int  # 0 (none) .. 100
    psr: float
    keyframe_id: int
    new_keyframe: bool
    reset_counter: int
    lost_reason: str | None
    shift_cells: tuple[float, float]
    tz_m: float
    res_m: float
    rotation_residual_rad: np.ndarray  # (3,) in key axes; z is not observed (0); NI-SLAM fills it after the pose (finish_frame)
    attitude_offset_s: float  # the attitude time offset the frame was tracked with [s]
    matched_cells: int
    finished_keyframes: tuple[KeyframeCloud, ...] = ()
    keyframe_reused: bool = False  # the frame switched to a key kept from before (not a new one)
    # The key this frame's pose was measured against (-1: not known, or no
    # single key): differs from `keyframe_id` on the frame that makes a new key.
    reference_keyframe_id: int = -1
    # The fused tracker (onboard.fusion.fused): the trackers whose motion this
    # frame's pose used, and (tracker, why) for each one left out.
    contributors: tuple[str, ...] = ()
    left_out: tuple[tuple[str, str], ...] = ()
    # The position relative to the reference key as the tracker measured it
    # (p_W_m minus that key's position in the tracker's world, W axes; None:
    # not known). Unlike p_W_m it does not move when the tracker refines or
    # re-uses keys, so the fused tracker can tell motion from a key's correction.
    reference_offset_m: np.ndarray | None = None
    # Loop closures that moved the map so far (FastORB): the pose jumps when
    # this goes up, as after a reset; the MAVLink feed announces it so.
    loop_corrections: int = 0
    # Key frames a loop closure moved, (id, p_W_m, R_W_C) each, on the first
    # result after it: the map's consumers re-place them (zenoh re-publishes).
    moved_keyframes: tuple[tuple[int, np.ndarray, np.ndarray], ...] = ()
    # NI-SLAM: the variance [m^2] the AHRS's attitude noise adds to each lateral
    # axis of the key's view (onboard.nislam.attitude_var; included in pose_var).
    attitude_var_m2: float = 0.0
    # The covariance (3x3, W, m^2) of this p_W_m minus the p_W_m this tracker
    # reported at an earlier frame of the same epoch: (that frame's t_s,
    # covariance) for each recent frame it can tell, oldest first. Unlike
    # pose_var (the fused tracker's is absolute: it grows with the drift) it
    # is what a velocity differenced from two poses needs; the MAVLink feed
    # uses it (mavlink_feed._twist). () = not known (the feed falls back to
    # the sum of the two pose_var). The fused tracker: onboard.fusion.displacement.
    displacement_cov: tuple[tuple[float, np.ndarray], ...] = ()
    # NI-SLAM decides after a pose whether a firm frame leaving its key's grid
    # (new_keyframe) starts a new key or a kept key is re-used instead: True
    # on the next result when the announced key was not made.
    keyframe_withdrawn: bool = False
    # NI-SLAM: a key was made inside this track() from the previous trusted
    # frame, because this frame no longer matched the old key at all; this
    # frame is then matched against it. Its key frame is the previous one,
    # not this (new_keyframe says that of a key made from this frame).
    keyframe_from_previous: bool = False

    @property
    def keyframes_added(self) -> int:
        """What this result adds to a count of key frames made."""
        return int(self.new_keyframe) + int(self.keyframe_from_previous) - int(self.keyframe_withdrawn)

    @property
    def q_W_C_xyzw(self) -> np.ndarray | None:
        return None if self.R_W_C is None else Rotation.from_matrix(self.R_W_C).as_quat()


class Tracker(Protocol):
    """One camera's tracking front end."""

    name: str

    def track(self, frame: RgbdFrame, attitude: AttitudeSource) -> TrackResult:
        """Track one frame; attitude is looked up at the frame's capture time."""
        ...

    def finish(self) -> KeyframeCloud | None:
        """End of a run: the current key's cloud for the map, if any."""
        ...


class Health(enum.Enum):
    STARTING = "starting"
    TRACKING = "tracking"
    DEGRADED = "degraded"
    LOST = "lost"


@dataclass(frozen=True)
class HealthReport:
    state: Health
    reason: str  # one line: why this state (shown in STATUSTEXT and zenoh status)
    changed: bool = False  # differs from the previous report's state
    devices: tuple[str, ...] = ()  # each driver's state ("OAK-D streaming", "myAHRS+ no device (...)")
