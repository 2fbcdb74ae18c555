"""The MAVLink vision-position feed to the flight controller.

Per tracked frame one ODOMETRY (or, selectable, VISION_POSITION_ESTIMATE +
VISION_SPEED_ESTIMATE), a HEARTBEAT at 1 Hz from component 197 telling how
tracking goes, a STATUSTEXT on every change of that, TIMESYNC answers and,
optionally, the EKF origin and home once at start. Facts behind every field:
../shared/docs/reference-flight-stack.md; the autopilot settings: README
"Integrating with ArduPilot and PX4".

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
               the tracker gives them; velocity variances propagated from
               the two poses

with R_B_C the camera mount (`mount`): "forward" (camera z = body x, camera
x = body y, camera y = body z), "down" (camera z = body z, the image top
towards the nose: camera y = -body x) or "custom" (`mount_q_B_C_xyzw`).

Time. `time_usec` is the frame's capture time (`TrackResult.t_s`), on the
host's monotonic clock when the frames come from the cameras (depthai stamps
with it). TIMESYNC requests (tc1 = 0) are answered with the same clock in
nanoseconds, so PX4 maps our stamps onto its own; ArduPilot jitter-corrects
them. (On a recording the stamps are the recording's.)

reset_counter (uint8, wraps) goes up by exactly one at the first pose after
the tracker's own reset_counter changed, after a lost spell, or when the
position steps further than `jump_m` faster than `jump_speed_m_s`. No pose is
ever sent for a frame the tracker does not trust.

State (HEARTBEAT system_status, quality):

    BOOT      1   no tracker result yet
    STANDBY   3   results, but no pose yet (initialising)       quality 0
    ACTIVE    4   tracking, quality >= degraded_quality          1-100
    CRITICAL  5   tracking, quality below it (back at +5)        1-100
    FLIGHT_TERMINATION 8  lost, or no result for `stale_s`        -1

When the onboard loop reports its health (`publish_health`, onboard/health.py:
starting, tracking, degraded, lost, which also weighs sensor freshness and
the fallback tracker), the HEARTBEAT carries that instead (STANDBY, ACTIVE,
CRITICAL, FLIGHT_TERMINATION), and each change goes out as a STATUSTEXT.

Threads. `publish()` only appends the result to a bounded queue (the oldest
is dropped when full) and wakes the sender thread, which owns the link:
it converts, sends, answers TIMESYNC (reading its own link every 2 ms),
keeps the heartbeat and reopens a link
that failed every `reconnect_s`, so the tracking loop never waits on a
socket or a serial port. Errors are counted and logged once per spell.
When the autopilot link is shared (drivers.fc_link.FcLink, which the
autopilot attitude source also reads), pass it as `link`: the feed then
sends through it and gets TIMESYNC requests from its reader thread.

pymavlink picks MAVLink 1 or 2 when it is first imported, from the
environment variable MAVLINK20; with MAVLink 1 ODOMETRY does not exist. This
module imports pymavlink only inside `load_mavutil()`, which sets
MAVLINK20=1 first, so importing onboard.mavlink_out has no side effect.
"""

from __future__ import annotations

import enum
import logging
import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from scipy.spatial.transform import Rotation

from onboard import NislamError
from onboard.config import MavlinkConfig
from onboard.frames import KeyframeCloud, TrackResult, TrackState
from onboard.geometry import so3_log
from onboard.health import Health, HealthReport

log = logging.getLogger(__name__)

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
RX_POLL_S = 0.002  # how often our own link is read: TIMESYNC answers within ~2 ms
QUALITY_HYSTERESIS = 5

# Camera optical axes (columns) in body FRD.
R_B_C_FORWARD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
R_B_C_DOWN = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
R_L_W = {"frd": np.eye(3), "flu": np.diag([1.0, -1.0, -1.0])}


def load_mavutil() -> Any:
    """pymavlink's mavutil with the MAVLink 2 messages.

    mavutil loads the MAVLink 2 dialect when MAVLINK20 is set (to anything)
    at its first import, so the variable is set here, right before that
    import. Something that imported pymavlink earlier without it got
    MAVLink 1, which is refused here rather than failing at the first send.
    """
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    if mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":
        raise NislamError(
            "pymavlink was loaded with MAVLink 1 (MAVLINK20 unset or 0 at its first import); "
            "ODOMETRY needs MAVLink 2"
        )
    return mavutil


def mount_rotation(mount: str, q_B_C_xyzw: tuple[float, ...] = (0.0, 0.0, 0.0, 1.0)) -> np.ndarray:
    """R_B_C for a mount preset, or the explicit quaternion for "custom"."""
    if mount == "forward":
        return R_B_C_FORWARD.copy()
    if mount == "down":
        return R_B_C_DOWN.copy()
    if mount == "custom":
        q = np.asarray(q_B_C_xyzw, dtype=np.float64)
        if not np.isfinite(q).all() or np.linalg.norm(q) < 1e-6:
            raise NislamError(f"mount quaternion {tuple(q)} is not a rotation")
        return Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()
    raise NislamError(f"unknown camera mount {mount!r} (forward, down, custom)")


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


# --------------------------------------------------------------------------- pure feed


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

_SEVERITY = {
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
    texts: tuple[tuple[int, str], ...] = ()  # (severity, STATUSTEXT) to send


@dataclass
class _Pose:
    t_s: float
    p_L: np.ndarray
    R_L_B: np.ndarray
    var: np.ndarray  # (6,)


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
    ) -> None:
        self.R_C_B = np.asarray(R_B_C, dtype=np.float64).T
        self.R_L_W = R_L_W[world_frame]
        self.degraded_quality = degraded_quality
        self.jump_m = jump_m
        self.jump_speed_m_s = jump_speed_m_s
        self.window_s = velocity_window_s
        self.state = FeedState.BOOT
        self.reset_counter = 0  # ours, as sent (uint8)
        self.resets = 0
        self._tracker_counter: int | None = None
        self._pending_reset: str | None = None  # why the next pose bumps the counter
        self._history: deque[_Pose] = deque()
        self._had_pose = False
        self._last_quality = 0

    @classmethod
    def from_config(cls, cfg: MavlinkConfig) -> VisionFeed:
        return cls(
            mount_rotation(cfg.mount, cfg.mount_q_B_C_xyzw), cfg.world_frame,
            cfg.degraded_quality, cfg.jump_m, cfg.jump_speed_m_s, cfg.velocity_window_s,
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
        pose = _Pose(result.t_s, p_L, R_L_B, var)
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

        v_L, v_var_L, w_B, w_var = self._twist(pose)
        self._history.append(pose)
        self._had_pose = True
        quality = int(min(100, max(1, result.quality)))
        self._last_quality = quality
        sample = VisionSample(
            time_usec=max(0, int(round(result.t_s * 1e6))),
            p_L_m=p_L,
            R_L_B=R_L_B,
            v_B_m_s=R_L_B.T @ v_L,
            v_L_m_s=v_L,
            w_B_rad_s=w_B,
            pose_var=var,
            twist_var_B=np.concatenate([(R_L_B.T**2) @ v_var_L, w_var]),
            v_var_L=v_var_L,
            reset_counter=self.reset_counter,
            quality=quality,
        )
        state = self._tracking_state(quality)
        word = "degraded" if state is FeedState.DEGRADED else "tracking"
        event = self._enter(sample, state, f"{word}, quality {quality}")
        if texts:
            return FeedEvent(event.sample, event.state, event.changed, tuple(texts) + event.texts)
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
        """Velocity in L and body rates against the oldest pose of this epoch
        at most `velocity_window_s` old, else the previous one; NaN when there
        is none. Poses older than the one used are no longer needed."""
        history = self._history
        ref = next((p for p in history if pose.t_s - p.t_s <= self.window_s), None)
        if ref is None and history:
            ref = history[-1]
        while history and history[0] is not ref:
            history.popleft()
        nan3 = np.full(3, np.nan)
        dt = math.nan if ref is None else pose.t_s - ref.t_s
        if not dt > 0:
            return nan3, nan3, nan3, nan3
        v_L = (pose.p_L - ref.p_L) / dt
        w_B = so3_log(ref.R_L_B.T @ pose.R_L_B) / dt
        return v_L, (pose.var[:3] + ref.var[:3]) / dt**2, w_B, (pose.var[3:] + ref.var[3:]) / dt**2

    def _enter(self, sample: VisionSample | None, state: FeedState, text: str) -> FeedEvent:
        changed = state is not self.state
        self.state = state
        texts = ((_SEVERITY[state], text),) if changed else ()
        return FeedEvent(sample, state, changed, texts)


# --------------------------------------------------------------------------- sender


@dataclass
class MavlinkStats:
    """Counters of the sender thread (read them with `MavlinkOutput.stats()`)."""

    results: int = 0
    dropped: int = 0  # results dropped from the full queue
    poses_sent: int = 0
    not_sent: int = 0  # poses that found the link down
    heartbeats: int = 0
    statustexts: int = 0
    timesync_replies: int = 0
    link_errors: int = 0
    link_opens: int = 0
    link_up: bool = False
    sent_by_type: dict[str, int] = field(default_factory=dict)


class SharedLink(Protocol):
    """A MAVLink connection owned by someone else (drivers.fc_link.FcLink):
    one link per autopilot, shared with the autopilot attitude source."""

    def send(self, build: Callable[[Any], object]) -> bool:
        """Run build(mav) under the link's write lock; False when it is down."""
        ...

    def add_listener(self, callback: Callable[[Any, int], object],
                     types: Iterable[str] | None = None) -> Callable[[], None]:
        """callback(msg, t_arrival_ns) for messages of `types`; returns a remover."""
        ...


class MavlinkOutput:
    """The feed on its own thread; see the module docstring. An `Output`.

    With `link` (a `SharedLink`) it sends and listens on that connection,
    which opens, reconnects and logs by itself; without, it opens
    `cfg.connect` and looks after it."""

    def __init__(
        self, cfg: MavlinkConfig, clock_ns: Callable[[], int] = time.monotonic_ns,
        link: SharedLink | None = None,
    ) -> None:
        self.cfg = cfg
        self._mavutil = load_mavutil()
        self._mav = self._mavutil.mavlink
        self.feed = VisionFeed.from_config(cfg)
        self._clock_ns = clock_ns
        self._queue: deque[TrackResult] = deque(maxlen=cfg.queue_frames)
        self._lock = threading.Lock()
        self._stats = MavlinkStats()
        self._stop = threading.Event()
        self._cond = threading.Condition()  # wake-ups only: held for an instant
        self._conn: Any = None
        self._link_dead: str | None = None
        self._next_open = 0.0
        self._spell: tuple[float, int] | None = None  # (start, errors) of a failure spell
        self._next_heartbeat = 0.0
        self._last_result_at: float | None = None
        self._origin_tries = 0
        self._origin_done = not cfg.set_origin
        self._next_origin = 0.0
        self._shared = link
        self._rx: deque[Any] = deque(maxlen=64)  # messages a shared link handed over
        self._health: FeedState | None = None  # the loop's health, when it reports one
        self._health_texts: deque[tuple[int, str, FeedState]] = deque(maxlen=8)
        self._remove_listener: Callable[[], None] | None = None
        if link is not None:
            self._remove_listener = link.add_listener(
                self._on_shared_message, ("TIMESYNC", "GPS_GLOBAL_ORIGIN"))
        self._thread = threading.Thread(target=self._run, name="mavlink-out", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------- Output API
    def publish(self, result: TrackResult) -> None:
        # deque.append is atomic and drops the oldest when full; the loop is
        # the only producer, so the drop count needs no lock either.
        if len(self._queue) == self._queue.maxlen:
            self._stats.dropped += 1
        self._queue.append(result)
        with self._cond:
            self._cond.notify()

    def publish_keyframe(self, cloud: KeyframeCloud) -> None:
        pass  # the flight controller has no use for the map

    def publish_health(self, report: HealthReport) -> None:
        state = HEALTH_STATE[report.state]
        if state is self._health and not report.changed:
            return
        self._health = state  # one attribute store: atomic; the sender reads it
        if report.changed:
            self._health_texts.append(
                (_SEVERITY[state], f"{report.state.value}: {report.reason}", state)
            )
        self._wake()

    def close(self, timeout_s: float = 2.0) -> None:
        """Send what is queued, then stop; the link closes with the thread."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._wake()
        self._thread.join(timeout_s)
        if self._remove_listener is not None:
            self._remove_listener()
        if self._thread.is_alive():
            log.warning("MAVLink sender did not stop within %.1f s (link %s busy)",
                        timeout_s, self.cfg.connect)

    def stats(self) -> dict[str, Any]:
        with self._lock:
            s = self._stats
            out = {k: getattr(s, k) for k in s.__dataclass_fields__}
            out["sent_by_type"] = dict(s.sent_by_type)
        out["state"] = self.feed.state.name
        out["system_status"] = self._system_status.name
        out["reset_counter"] = self.feed.reset_counter
        return out

    def __enter__(self) -> MavlinkOutput:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------- the thread
    def _wake(self) -> None:
        # A condition, not a pipe: notify() makes no system call that would let
        # the woken thread take the GIL in the middle of the loop's publish().
        with self._cond:
            self._cond.notify()

    def _on_shared_message(self, msg: Any, _t_ns: int) -> None:
        self._rx.append(msg)  # on the link's reader thread: hand over, wake, return
        self._wake()

    @property
    def _link_open(self) -> bool:
        return self._shared is not None or self._conn is not None

    def _run(self) -> None:
        if self._shared is not None:
            self._heartbeat()  # BOOT until the first result
        try:
            while True:
                stopping = self._stop.is_set()
                self._step(stopping)
                if stopping:
                    break
        except Exception:  # a bug: log it, the loop keeps running without us
            log.exception("MAVLink sender stopped")
        finally:
            self._close_link()

    def _step(self, stopping: bool) -> None:
        now = time.monotonic()
        if not self._link_open and now >= self._next_open:
            self._open_link(now)
        if not stopping:
            self._wait(now)
        if self._link_open:
            self._receive()
        while self._health_texts:
            severity, text, state = self._health_texts.popleft()
            self._statustext(severity, text)
            # Each change's own state at once, even when the next change came
            # before this thread woke (a first frame that tracks at once would
            # otherwise never show STANDBY).
            self._heartbeat(state)
        while self._queue:
            result = self._queue.popleft()
            with self._lock:
                self._stats.results += 1
            self._last_result_at = time.monotonic()
            self._handle(self.feed.update(result))
        now = time.monotonic()
        last = self._last_result_at
        if last is not None and now - last > self.cfg.stale_s:
            event = self.feed.stale(now - last)
            if event is not None:
                self._handle(event)
        if now >= self._next_heartbeat:
            self._heartbeat()
        if not self._origin_done and self._link_open and now >= self._next_origin:
            self._send_origin(now)

    def _wait(self, now: float) -> None:
        deadlines = [self._next_heartbeat]
        if not self._link_open:
            deadlines.append(self._next_open)
        elif not self._origin_done:
            deadlines.append(self._next_origin)
        watching = self.feed.state not in (FeedState.BOOT, FeedState.LOST)
        if watching and self._last_result_at is not None:
            deadlines.append(self._last_result_at + self.cfg.stale_s + 1e-3)
        timeout = min(0.5, max(0.0, min(deadlines) - now))
        if self._conn is not None:
            timeout = min(timeout, RX_POLL_S)  # our own link: look for TIMESYNC requests
        with self._cond:
            idle = not (self._queue or self._rx or self._health_texts)
            if idle and not self._stop.is_set():
                self._cond.wait(timeout)

    # ------------------------------------------------------------- link
    def _open_link(self, now: float) -> None:
        try:
            conn = self._mavutil.mavlink_connection(
                self.cfg.connect, baud=self.cfg.baud, source_system=self.cfg.system_id,
                source_component=self.cfg.component_id, autoreconnect=False, retries=0,
            )
        except Exception as e:  # noqa: BLE001 - OSError, SerialException, socket errors
            self._failed(f"cannot open: {e}", now)
            return
        # pymavlink reports a closed TCP peer with print() and carries on
        # without autoreconnect; route that into our reopen logic instead.
        if hasattr(conn, "handle_eof"):
            conn.handle_eof = lambda: self._mark_dead("closed by the peer")
            conn.handle_disconnect = lambda: self._mark_dead("connection reset")
        port = getattr(conn, "port", None)
        if port is not None and hasattr(port, "write_timeout"):
            port.write_timeout = 0.05  # a serial port that stops draining fails, not blocks
        self._conn = conn
        self._link_dead = None
        with self._lock:
            self._stats.link_up = True
            self._stats.link_opens += 1
        if self._spell is not None:
            start, errors = self._spell
            log.warning("MAVLink link %s open again after %.1f s (%d errors)",
                        self.cfg.connect, now - start, errors)
            self._spell = None
        else:
            log.info("MAVLink link %s open", self.cfg.connect)
        self._heartbeat()  # announce ourselves (BOOT until the first result) at once

    def _mark_dead(self, reason: str) -> None:
        self._link_dead = self._link_dead or reason

    def _failed(self, reason: str, now: float) -> None:
        """Count an error; log the first of a spell; reopen later."""
        with self._lock:
            self._stats.link_errors += 1
            self._stats.link_up = False
        if self._spell is None:
            self._spell = (now, 1)
            log.warning("MAVLink link %s: %s; retrying every %.1f s",
                        self.cfg.connect, reason, self.cfg.reconnect_s)
        else:
            self._spell = (self._spell[0], self._spell[1] + 1)
        self._close_link()
        self._next_open = now + self.cfg.reconnect_s

    def _close_link(self) -> None:
        conn, self._conn = self._conn, None
        if conn is not None:
            try:
                conn.close()
            except Exception:  # noqa: BLE001 - closing a broken port may fail too
                pass

    def _send(self, name: str, *args: Any) -> bool:
        """Call `mav.<name>_send(*args)`; False (and the link reopens) on failure."""
        if self._shared is not None:
            ok = self._shared.send(lambda mav: getattr(mav, name + "_send")(*args))
            if ok:
                with self._lock:
                    counts = self._stats.sent_by_type
                    counts[name] = counts.get(name, 0) + 1
            return ok
        conn = self._conn
        if conn is None:
            return False
        try:
            getattr(conn.mav, name + "_send")(*args)
        except Exception as e:  # noqa: BLE001 - socket, serial and struct errors alike
            self._failed(f"send failed: {e}", time.monotonic())
            return False
        dead = self._link_dead or ("port dead" if getattr(conn, "portdead", False) else None)
        if dead is not None:
            self._failed(dead, time.monotonic())
            return False
        with self._lock:
            counts = self._stats.sent_by_type
            counts[name] = counts.get(name, 0) + 1
        return True

    def _receive(self) -> None:
        """Answer TIMESYNC requests; note the origin's confirmation."""
        if self._shared is not None:
            while self._rx:
                self._on_message(self._rx.popleft())
            return
        for _ in range(100):
            conn = self._conn
            if conn is None:
                return
            try:
                msg = conn.recv_msg()
            except Exception as e:  # noqa: BLE001
                self._failed(f"receive failed: {e}", time.monotonic())
                return
            if self._link_dead is not None:
                self._failed(self._link_dead, time.monotonic())
                return
            if msg is None:
                return
            self._on_message(msg)

    def _on_message(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "TIMESYNC" and msg.tc1 == 0:
            if self._send("timesync", self._clock_ns(), msg.ts1):
                with self._lock:
                    self._stats.timesync_replies += 1
        elif kind == "GPS_GLOBAL_ORIGIN" and not self._origin_done:
            self._origin_done = True
            log.info("autopilot confirmed the EKF origin")

    # ------------------------------------------------------------- messages
    def _handle(self, event: FeedEvent) -> None:
        for severity, text in event.texts:
            self._statustext(severity, text)
        if event.changed:
            self._heartbeat()
        if event.sample is None:
            return
        sent = (self._send_odometry(event.sample) if self.cfg.message == "odometry"
                else self._send_vision(event.sample))
        with self._lock:
            if sent:
                self._stats.poses_sent += 1
            else:
                self._stats.not_sent += 1

    def _send_odometry(self, s: VisionSample) -> bool:
        return self._send(
            "odometry", s.time_usec, MAV_FRAME_LOCAL_FRD, MAV_FRAME_BODY_FRD,
            *s.p_L_m.tolist(), s.q_wxyz.tolist(), *s.v_B_m_s.tolist(), *s.w_B_rad_s.tolist(),
            diag_cov21(s.pose_var), diag_cov21(s.twist_var_B), s.reset_counter,
            MAV_ESTIMATOR_TYPE_VIO, s.quality,
        )

    def _send_vision(self, s: VisionSample) -> bool:
        ok = self._send(
            "vision_position_estimate", s.time_usec, *s.p_L_m.tolist(),
            *euler_rpy(s.R_L_B).tolist(), diag_cov21(s.pose_var), s.reset_counter,
        )
        if ok and np.all(np.isfinite(s.v_L_m_s)):
            cov9 = [0.0] * 9
            cov9[0], cov9[4], cov9[8] = (float(v) for v in s.v_var_L)
            ok = self._send("vision_speed_estimate", s.time_usec, *s.v_L_m_s.tolist(), cov9,
                            s.reset_counter)
        return ok

    @property
    def _system_status(self) -> FeedState:
        return self._health if self._health is not None else self.feed.state

    def _heartbeat(self, state: FeedState | None = None) -> None:
        self._next_heartbeat = time.monotonic() + self.cfg.heartbeat_period_s
        state = self._system_status if state is None else state
        if self._send("heartbeat", MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0,
                      state.mav_state):
            with self._lock:
                self._stats.heartbeats += 1

    def _statustext(self, severity: int, text: str) -> None:
        data = ("NISLAM: " + text).encode("ascii", "replace")[:STATUSTEXT_LEN]
        log.info("status: %s", data.decode("ascii"))
        if self._send("statustext", severity, data):
            with self._lock:
                self._stats.statustexts += 1

    def _send_origin(self, now: float) -> None:
        """SET_GPS_GLOBAL_ORIGIN + SET_HOME_POSITION, repeated each second until
        the autopilot answers GPS_GLOBAL_ORIGIN (5 tries at most)."""
        c = self.cfg
        lat, lon, alt = round(c.origin_lat_deg * 1e7), round(c.origin_lon_deg * 1e7), round(
            c.origin_alt_m * 1e3)
        t_us = self._clock_ns() // 1000
        self._send("set_gps_global_origin", c.system_id, lat, lon, alt, t_us)
        self._send("set_home_position", c.system_id, lat, lon, alt, 0.0, 0.0, 0.0,
                   [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, t_us)
        self._origin_tries += 1
        self._next_origin = now + 1.0
        if self._origin_tries >= 5:
            self._origin_done = True
