"""The vision-position feed as the flight controller sees it, pure: tracker
results in, the MAVLink samples, state and texts out (no I/O, no clock), so it
is tested on its own. onboard.outputs.mavlink sends them.

Frames. The tracker reports the camera (optical frame C) in its world W, the
AHRS world: gravity-aligned, z down, heading that of the AHRS. That is
MAVLink's LOCAL_FRD (earth-fixed, z down, arbitrary heading), so the local
frame L is W itself (`world_frame = "frd"`). A world with z up (a
motion-capture world, e.g. TUM replays; `"flu"`) is turned into L by a
half turn about x: R_L_W = diag(1, -1, -1). Then

    position   p_L = R_L_W p_W                 the sensor's position: the
               camera's offset on the body is left to the autopilot
               (VISO_POS_*, EKF2_EV_POS_*), never applied twice
    attitude   R_L_B = R_L_W R_W_C R_B_C^T     body FRD to L, sent as q (w, x, y, z)
    velocity   v_B = R_L_B^T (p_L(k) - p_L(j)) / (t_k - t_j), body FRD, from
               the pose up to `velocity_window_s` earlier in the same epoch;
               NaN (unknown) on the first pose after a (re)start: both
               stacks skip a NaN velocity
    covariance diagonal of the 6x6 upper triangle, indices 0, 6, 11, 15, 18,
               20: position variances rotated into L, attitude variances as
               the tracker gives them; velocity variances those of the
               displacement p(k) - p(j) over dt^2 (`_twist`): the tracker's
               covariance of that displacement when it tells one
               (`TrackResult.displacement_cov`), else the two poses' summed

with R_B_C the camera mount (`mount`): "forward" (camera z = body x, camera
x = body y, camera y = body z), "down" (camera z = body z, the image top
towards the nose: camera y = -body x) or "custom" (`mount_q_B_C_xyzw`).

Time. `time_usec` is the frame's capture time on the host's monotonic clock
(CLOCK_MONOTONIC, shared by every process of one boot), so it only ever
increases, across replays and restarts too. Cameras stamp with that clock
(depthai does); a replayed recording keeps its own stamps in
`TrackResult.t_s` (and in the trajectories written), and `host_time_s` maps
them onto the monotonic time the replay reached them. TIMESYNC requests
(tc1 = 0) are answered with the same clock in nanoseconds, so PX4 maps our
stamps onto its own; ArduPilot jitter-corrects them.

reset_counter (uint8, wraps) starts at `start_counter` (one above the last
one an earlier process sent: onboard.outputs.mavlink_origin), so the first
pose of a new process, whose world starts at that pose, announces a new
origin; it goes up by exactly one at the first pose after the tracker's own
reset_counter changed, after a loop closure moved the tracker's map
(`TrackResult.loop_corrections` changed: the pose steps by the drift it
removed, which the autopilot must not fuse as motion; docs/autopilot.md),
after a lost spell, or when the position steps further than `jump_m`
faster than `jump_speed_m_s`. No pose is ever sent for
a frame the tracker does not trust.

State (HEARTBEAT system_status, quality):

    BOOT      1   no tracker result yet
    STANDBY   3   results, but no pose yet (initialising)       quality 0
    ACTIVE    4   tracking, quality >= degraded_quality          1-100
    CRITICAL  5   tracking, quality below it (back at +5)        1-100
    FLIGHT_TERMINATION 8  lost, or no result for `stale_s`        -1

When the onboard loop reports its health (`publish_health`, onboard/app/health.py:
starting, tracking, degraded, lost, which also weighs sensor freshness and
the fallback tracker), the HEARTBEAT carries that instead (STANDBY, ACTIVE,
CRITICAL, FLIGHT_TERMINATION), and each change goes out as a STATUSTEXT.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from onboard.core.messages import Health, TrackResult, TrackState
from onboard.core.rotations import mount_rotation, so3_log
from onboard.outputs.settings import MavlinkConfig

# MAVLink constants (common.xml), named here so the pure part needs no pymavlink.
MAV_FRAME_LOCAL_FRD = 20


MAV_FRAME_BODY_FRD = 12


MAV_ESTIMATOR_TYPE_VIO = 3


MAV_TYPE_ONBOARD_CONTROLLER = 18


MAV_AUTOPILOT_INVALID = 8


MAV_SEVERITY_CRITICAL = 2


MAV_SEVERITY_WARNING = 4


MAV_SEVERITY_NOTICE = 5


MAV_SEVERITY_INFO = 6


STATUSTEXT_LEN = 50


QUALITY_HYSTERESIS = 5


R_L_W = {"frd": np.eye(3), "flu": np.diag([1.0, -1.0, -1.0])}


def q_wxyz(r: np.ndarray) -> np.ndarray:
    """MAVLink quaternion (w, x, y, z) of a rotation matrix, w >= 0."""
    x, y, z, w = Rotation.from_matrix(r).as_quat(canonical=True)
    return np.array([w, x, y, z])


def euler_rpy(r: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (Z-Y-X Tait-Bryan, as MAVLink's ATTITUDE) of R_L_B."""
    pitch = -math.asin(max(-1.0, min(1.0, float(r[2, 0]))))
    return np.array([math.atan2(r[2, 1], r[2, 2]), pitch, math.atan2(r[1, 0], r[0, 0])])


def diag_cov21(var6: np.ndarray) -> list[float]:
    """The 21-element upper triangle of a diagonal 6x6 covariance; NaN at
    index 0 (= unknown) when any variance is not finite."""
    cov = [0.0] * 21
    if not np.all(np.isfinite(var6)):
        cov[0] = math.nan
        return cov
    for value, index in zip(var6, (0, 6, 11, 15, 18, 20)):
        cov[index] = float(value)
    return cov


class FeedState(enum.Enum):
    BOOT = 1  # values: MAV_STATE
    STANDBY = 3
    ACTIVE = 4
    DEGRADED = 5  # MAV_STATE_CRITICAL
    LOST = 8  # MAV_STATE_FLIGHT_TERMINATION

    @property
    def mav_state(self) -> int:
        return self.value


HEALTH_STATE = {  # onboard health -> the HEARTBEAT's system_status
    Health.STARTING: FeedState.STANDBY,
    Health.TRACKING: FeedState.ACTIVE,
    Health.DEGRADED: FeedState.DEGRADED,
    Health.LOST: FeedState.LOST,
}


SEVERITY = {
    FeedState.BOOT: MAV_SEVERITY_INFO,
    FeedState.STANDBY: MAV_SEVERITY_INFO,
    FeedState.ACTIVE: MAV_SEVERITY_INFO,
    FeedState.DEGRADED: MAV_SEVERITY_WARNING,
    FeedState.LOST: MAV_SEVERITY_CRITICAL,
}


@dataclass(frozen=True)
class VisionSample:
    """One frame's feed, in LOCAL_FRD (L) and body FRD (B); NaN = unknown."""

    time_usec: int
    p_L_m: np.ndarray  # (3,) sensor position
    R_L_B: np.ndarray  # (3, 3)
    v_B_m_s: np.ndarray  # (3,)
    v_L_m_s: np.ndarray  # (3,)
    w_B_rad_s: np.ndarray  # (3,) body rates
    pose_var: np.ndarray  # (6,) x, y, z [m^2] in L; roll, pitch, yaw [rad^2]
    twist_var_B: np.ndarray  # (6,) vx, vy, vz [(m/s)^2] in B; rates [(rad/s)^2]
    v_var_L: np.ndarray  # (3,) [(m/s)^2] in L
    reset_counter: int
    quality: int

    @property
    def q_wxyz(self) -> np.ndarray:
        return q_wxyz(self.R_L_B)


@dataclass(frozen=True)
class FeedEvent:
    """What one result (or a silence) means for the link."""

    sample: VisionSample | None  # a pose to send, or None
    state: FeedState
    changed: bool  # the state differs from the previous one
    texts: tuple[tuple[int, str], ...] = ()  # (severity, STATUSTEXT) of the state change
    notices: tuple[tuple[int, str], ...] = ()  # (severity, STATUSTEXT) of a reset


@dataclass
class _Pose:
    t_s: float
    p_L: np.ndarray
    R_L_B: np.ndarray
    var: np.ndarray  # (6,)
    # t_s of an earlier frame -> Cov(p_L(this) - p_L(that)) (3x3), as the tracker tells it
    disp: dict[float, np.ndarray]


class VisionFeed:
    """Tracker results in, the feed's samples and state out. Pure: no I/O,
    no clock (time comes with the results), so it is tested on its own."""

    def __init__(
        self,
        R_B_C: np.ndarray,
        world_frame: str = "frd",
        degraded_quality: int = 20,
        jump_m: float = 0.1,
        jump_speed_m_s: float = 10.0,
        velocity_window_s: float = 0.1,
        start_counter: int = 0,
        host_time_s: Callable[[float], float] | None = None,
    ) -> None:
        self.R_C_B = np.asarray(R_B_C, dtype=np.float64).T
        self.R_L_W = R_L_W[world_frame]
        self.degraded_quality = degraded_quality
        self.jump_m = jump_m
        self.jump_speed_m_s = jump_speed_m_s
        self.window_s = velocity_window_s
        self.state = FeedState.BOOT
        self.reset_counter = start_counter % 256  # ours, as sent (uint8)
        self.host_time_s = host_time_s  # frame stamp -> host monotonic time (None: the same)
        self.resets = 0
        self._tracker_counter: int | None = None
        self._loop_counter: int | None = None
        self._pending_reset: str | None = None  # why the next pose bumps the counter
        self._history: deque[_Pose] = deque()
        self._had_pose = False
        self._last_quality = 0

    @classmethod
    def from_config(cls, cfg: MavlinkConfig, start_counter: int = 0,
                    host_time_s: Callable[[float], float] | None = None) -> VisionFeed:
        return cls(
            mount_rotation(cfg.mount, cfg.mount_q_B_C_xyzw), cfg.world_frame,
            cfg.degraded_quality, cfg.jump_m, cfg.jump_speed_m_s, cfg.velocity_window_s,
            start_counter, host_time_s,
        )

    @property
    def quality(self) -> int:
        """-1 lost, 0 starting, else the last pose's 1-100 (ODOMETRY.quality)."""
        if self.state is FeedState.LOST:
            return -1
        if self.state in (FeedState.BOOT, FeedState.STANDBY):
            return 0
        return self._last_quality

    def update(self, result: TrackResult) -> FeedEvent:
        if self._tracker_counter is not None and result.reset_counter != self._tracker_counter:
            self._pending_reset = self._pending_reset or "tracker reset"
        self._tracker_counter = result.reset_counter
        if self._loop_counter is not None and result.loop_corrections != self._loop_counter:
            self._pending_reset = self._pending_reset or "loop closure"
        self._loop_counter = result.loop_corrections
        if not result.trusted or result.p_W_m is None or result.R_W_C is None:
            return self._untrusted(result)
        return self._trusted(result)

    def stale(self, silence_s: float) -> FeedEvent | None:
        """No result for `silence_s`: lost ("no frames"), once."""
        if self.state in (FeedState.BOOT, FeedState.LOST):
            return None
        if self._had_pose:
            self._pending_reset = self._pending_reset or "lost"
        self._history.clear()
        return self._enter(None, FeedState.LOST, f"lost: no frames for {silence_s:.1f} s")

    # ------------------------------------------------------------------ steps
    def _untrusted(self, result: TrackResult) -> FeedEvent:
        if not self._had_pose and result.state is not TrackState.LOST:
            return self._enter(None, FeedState.STANDBY, "initialising")
        if self._had_pose:
            self._pending_reset = self._pending_reset or "lost"
        self._history.clear()
        return self._enter(None, FeedState.LOST, f"lost: {result.lost_reason or 'untrusted'}")

    def _trusted(self, result: TrackResult) -> FeedEvent:
        p_L = self.R_L_W @ np.asarray(result.p_W_m, dtype=np.float64)
        R_L_B = self.R_L_W @ np.asarray(result.R_W_C, dtype=np.float64) @ self.R_C_B
        var = np.asarray(result.pose_var, dtype=np.float64).copy()
        var[:3] = (self.R_L_W**2) @ var[:3]
        disp = {t_j: self.R_L_W @ np.asarray(C, dtype=np.float64) @ self.R_L_W.T
                for t_j, C in result.displacement_cov}
        pose = _Pose(result.t_s, p_L, R_L_B, var, disp)
        texts: list[tuple[int, str]] = []

        jump = self._jump(pose)
        if jump is not None:
            self._pending_reset = self._pending_reset or jump
        if self._pending_reset is not None:
            if self._had_pose:
                self.reset_counter = (self.reset_counter + 1) % 256
                self.resets += 1
                texts.append((MAV_SEVERITY_NOTICE,
                              f"reset {self.reset_counter}: {self._pending_reset}"))
            self._pending_reset = None
            self._history.clear()

        v_L, v_cov_L, w_B, w_var = self._twist(pose)
        v_var_L = np.diag(v_cov_L).copy()
        self._history.append(pose)
        self._had_pose = True
        quality = int(min(100, max(1, result.quality)))
        self._last_quality = quality
        t_host_s = result.t_s if self.host_time_s is None else self.host_time_s(result.t_s)
        sample = VisionSample(
            time_usec=max(0, int(round(t_host_s * 1e6))),
            p_L_m=p_L,
            R_L_B=R_L_B,
            v_B_m_s=R_L_B.T @ v_L,
            v_L_m_s=v_L,
            w_B_rad_s=w_B,
            pose_var=var,
            twist_var_B=np.concatenate([np.diag(R_L_B.T @ v_cov_L @ R_L_B), w_var]),
            v_var_L=v_var_L,
            reset_counter=self.reset_counter,
            quality=quality,
        )
        state = self._tracking_state(quality)
        word = "degraded" if state is FeedState.DEGRADED else "tracking"
        event = self._enter(sample, state, f"{word}, quality {quality}")
        if texts:
            return FeedEvent(event.sample, event.state, event.changed, event.texts, tuple(texts))
        return event

    def _tracking_state(self, quality: int) -> FeedState:
        if self.state is FeedState.DEGRADED:
            back = quality >= self.degraded_quality + QUALITY_HYSTERESIS
            return FeedState.ACTIVE if back else FeedState.DEGRADED
        return FeedState.DEGRADED if quality < self.degraded_quality else FeedState.ACTIVE

    def _jump(self, pose: _Pose) -> str | None:
        if not self._history:
            return None
        prev = self._history[-1]
        step = float(np.linalg.norm(pose.p_L - prev.p_L))
        dt = pose.t_s - prev.t_s
        if step > self.jump_m and (dt <= 0 or step / dt > self.jump_speed_m_s):
            return f"jump {step:.2f} m"
        return None

    def _twist(self, pose: _Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Velocity in L with its covariance (3x3) and body rates with their
        variances, against the oldest pose of this epoch at most
        `velocity_window_s` old, else the previous one; NaN when there is
        none. Poses older than the one used are no longer needed.

        v = (p_k - p_j) / dt, so Cov(v) = Cov(p_k - p_j) / dt^2, and
        Cov(p_k - p_j) = Var(p_k) + Var(p_j) - Cov(p_k, p_j) - Cov(p_j, p_k).
        The cross terms are what the tracker knows and the feed does not: two
        poses measured against the same key share the key's error, and a
        filter's two outputs share all the drift before the first, so with
        absolute variances (the fused tracker's grow with the drift) the sum
        alone says the velocity gets worse over the flight while its
        displacement over 0.1 s stays as precise. So the tracker's own
        covariance of this displacement is used when it tells one for pose j
        (`TrackResult.displacement_cov`; the fused tracker's from a clone of
        its output at j: onboard.fusion.displacement); otherwise the
        cross terms are taken as zero: Var(p_k) + Var(p_j), right for
        independent errors (a tracker whose pose_var is a frame's own)."""
        history = self._history
        ref = next((p for p in history if pose.t_s - p.t_s <= self.window_s), None)
        if ref is None and history:
            ref = history[-1]
        while history and history[0] is not ref:
            history.popleft()
        nan3 = np.full(3, np.nan)
        dt = math.nan if ref is None else pose.t_s - ref.t_s
        if not dt > 0:
            return nan3, np.full((3, 3), np.nan), nan3, nan3
        v_L = (pose.p_L - ref.p_L) / dt
        w_B = so3_log(ref.R_L_B.T @ pose.R_L_B) / dt
        disp = pose.disp.get(ref.t_s)
        if disp is None or not np.all(np.isfinite(disp)):
            disp = np.diag(pose.var[:3] + ref.var[:3])
        return v_L, disp / dt**2, w_B, (pose.var[3:] + ref.var[3:]) / dt**2

    def _enter(self, sample: VisionSample | None, state: FeedState, text: str) -> FeedEvent:
        changed = state is not self.state
        self.state = state
        texts = ((SEVERITY[state], text),) if changed else ()
        return FeedEvent(sample, state, changed, texts)


def odometry_args(s: VisionSample) -> tuple:
    """ODOMETRY's fields for `mav.odometry_send` / `odometry_encode`, in order."""
    return (
        s.time_usec, MAV_FRAME_LOCAL_FRD, MAV_FRAME_BODY_FRD,
        *s.p_L_m.tolist(), s.q_wxyz.tolist(), *s.v_B_m_s.tolist(), *s.w_B_rad_s.tolist(),
        diag_cov21(s.pose_var), diag_cov21(s.twist_var_B), s.reset_counter,
        MAV_ESTIMATOR_TYPE_VIO, s.quality,
    )
