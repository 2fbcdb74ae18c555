"""Replay drivers: a recorded TUM-layout sequence played at real-time pace
through the same interfaces as the hardware drivers.

- `ReplayClock` maps our monotonic clock onto the recording's time base, so
  replayed stamps stay the recording's own (`host_time_s` maps them back:
  the MAVLink feed stamps on the host's clock).
- `ReplayCamera` is a `onboard.core.sources.CameraSource`: it publishes each frame
  into a newest-frame slot FRAME_DELIVERY_S after the replay clock reaches
  its stamp (decoding it just before that, `DecodeLead`), and closes the
  slot after the last one.
- `ReplayAttitude` pushes `AttitudeSample`s (R_W_B) into a sink when the
  clock reaches their stamps: `attitude.txt` (AHRS body in W) when the
  sequence has one, else ground truth (the camera's own orientation, mount
  identity, as replays of TUM data do).

`open_replay(seq_dir, ...)` builds the three on one clock. With `loop_s`
the recording plays forwards, backwards, forwards, ... (`pingpong_schedule`):
the camera's path stays continuous at every turn, so a soak test can run for
as long as it likes on one recording.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from onboard import NislamError
from onboard.core.attitude import AttitudeBuffer, AttitudeSample
from onboard.core.attitude_smoothing import DEFAULT_HALF_S, DEFAULT_MAX_HALF_S
from onboard.core.camera import CameraModel
from onboard.core.messages import RgbdFrame
from onboard.core.rotations import quat_to_matrix
from onboard.core.sources import DriverThread, FrameSlot
from sim_replay.attitude import recorded_noise_deg
from sim_replay.stamps import DEFAULT_WINDOW_S
from sim_replay.tum import Sequence, open_sequence

log = logging.getLogger(__name__)

PREROLL_S = 0.2  # attitude plays this long before the first frame
TAIL_S = 0.2  # ... and this long after the last one
# A camera hands a frame over some time after its capture (exposure, readout,
# USB): replayed frames appear this long after their stamps, so the AHRS
# samples after the capture time are there too, as live. 33 ms is the OAK's
# own figure: Luxonis measure 33 ms from the frame's timestamp (getTimestamp,
# host clock) to the host for colour at 1080p 60 fps over USB 3 ("Optimizing
# FPS & Latency", depthai docs; mono 400p alone: 7.5 ms). That timestamp is
# the end of the exposure; drivers/oak.py stamps its middle, which adds half
# the exposure. The flight setup (640x400 colour at 30 fps: fewer bytes, but
# stereo depth aligned to it and a host Sync node that releases the pair when
# the slower one is in) may be quicker or slower: not measured on our device
# yet; replace it with `nislam run`'s `source` stage on one (docs/latency.md).
FRAME_DELIVERY_S = 0.033
# The longest the camera thread waits for the loop to take a frame before it
# goes on to the next (a loop still busy with the last frame): a third of a
# 30 Hz frame period, leaving the decoding (~10 ms here) the rest.
HANDOVER_WAIT_S = 0.010


class DecodeLead:
    """How long before a frame's delivery the replay camera starts decoding
    it: 1.5x the slowest of the last `n` decodes + 3 ms (wall time); at once
    while none was timed.

    A camera's driver thread converts a frame when it arrives and hands it
    over; the OAK's then sleeps on its device queue until the next one, so
    nothing of it runs while the loop tracks. The replay decoded the next
    frame right after the hand-over instead, beside the tracker: on the 2-core
    VM that doubled the tracker's wall time (30 s `circle`: p50 7.4 ms against
    3.8 ms of CPU) and put 4 ms on every pose's latency (docs/latency.md,
    "Stop 33"). Started this much before the delivery, the decoding falls in
    the loop's idle time unless the tracker takes most of a frame period."""

    def __init__(self, n: int = 30, factor: float = 1.5, extra_s: float = 0.003) -> None:
        self._decode_s: deque[float] = deque(maxlen=n)
        self.factor = factor
        self.extra_s = extra_s

    def add(self, decode_s: float) -> None:
        self._decode_s.append(decode_s)

    @property
    def lead_s(self) -> float:
        if not self._decode_s:
            return math.inf
        return self.factor * max(self._decode_s) + self.extra_s


class ReplayClock:
    """Recording time = `t0_s` + (monotonic now - start) * `speed`, once started."""

    def __init__(self, t0_s: float, speed: float = 1.0,
                 mono_ns: Callable[[], int] = time.monotonic_ns) -> None:
        if speed <= 0:
            raise ValueError("replay speed must be > 0")
        self.t0_s = float(t0_s)
        self.speed = float(speed)
        self.mono_ns = mono_ns
        self._start_ns: int | None = None
        self._lock = threading.Lock()

    def start(self) -> None:
        """Start the clock (first call wins; later calls keep the first start)."""
        with self._lock:
            if self._start_ns is None:
                self._start_ns = self.mono_ns()

    def now_s(self) -> float:
        start = self._start_ns
        if start is None:
            return self.t0_s
        return self.t0_s + (self.mono_ns() - start) * 1e-9 * self.speed

    def now_ns(self) -> int:
        """Recording time in ns."""
        return int(round(self.now_s() * 1e9))

    def host_time_s(self, t_s: float) -> float:
        """The monotonic time [s] (the `mono_ns` clock) at which the replay
        reaches recording time `t_s`: where a live camera would have stamped
        the frame. Before start() the clock is taken as starting now."""
        start = self._start_ns
        if start is None:
            start = self.mono_ns()
        return start * 1e-9 + (t_s - self.t0_s) / self.speed

    def host_mapping(self) -> dict[str, float] | None:
        """host time = host_t0_s + (recording time - recording_t0_s) / speed,
        for metrics.json (None before start)."""
        start = self._start_ns
        if start is None:
            return None
        return {"recording_t0_s": self.t0_s, "host_t0_s": start * 1e-9, "speed": self.speed}

    def wait_until(self, t_s: float, stop: threading.Event) -> bool:
        """Wait until recording time `t_s`; False if `stop` was set first."""
        while True:
            remaining = (t_s - self.now_s()) / self.speed
            if remaining <= 0:
                return not stop.is_set()
            if stop.wait(min(remaining, 0.5)):
                return False


def pass_direction(index: np.ndarray, k: int) -> int:
    """+1 when schedule entry k plays its pass forwards, -1 backwards (a
    pass's first entry repeats the previous pass's last index)."""
    d = int(index[k]) - int(index[k - 1]) if k > 0 else 0
    if d == 0 and k + 1 < len(index):
        d = int(index[k + 1]) - int(index[k])
    return -1 if d < 0 else 1


def played_frame(frame: RgbdFrame, t_play: float, direction: int) -> RgbdFrame:
    """The frame stamped with its played time; the depth's own stamp moves
    with it through the same map (mirrored on a backward pass, as the
    attitude samples are): left on the recording's clock, every frame of a
    second pass asked the attitude for a time long gone ("no attitude")."""
    depth_t = frame.depth_t_s
    if depth_t is not None:
        depth_t = t_play + direction * (depth_t - frame.t_s)
    return dataclasses.replace(frame, t_s=t_play, depth_t_s=depth_t)


def pingpong_schedule(t_s: np.ndarray, passes: int, span_s: tuple[float, float],
                      gap_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(index into `t_s`, played stamp) for `passes` alternating passes over
    the increasing stamps `t_s` within `span_s` = (first, last): forwards, then
    backwards in time mirrored onto a continuing clock, and so on, `gap_s`
    between passes so the played stamps increase strictly. Frames and attitude
    samples use the same span and gap, so they stay paired."""
    t = np.asarray(t_s, dtype=np.float64)
    first, last = span_s
    inside = np.flatnonzero((t >= first) & (t <= last))
    period = last - first + gap_s
    idx, played = [], []
    for k in range(passes):
        order = inside if k % 2 == 0 else inside[::-1]
        local = t[order] - first if k % 2 == 0 else last - t[order]
        idx.append(order)
        played.append(first + k * period + local)
    return np.concatenate(idx), np.concatenate(played)


class ReplayCamera(DriverThread):
    """Frames of `seq` at their stamps into a FrameSlot (a CameraSource);
    `schedule` (index, played stamp) replays them in another order."""

    def __init__(self, seq: Sequence, clock: ReplayClock, camera: CameraModel | None = None,
                 delivery_s: float = FRAME_DELIVERY_S,
                 schedule: tuple[np.ndarray, np.ndarray] | None = None,
                 handover_wait_s: float = HANDOVER_WAIT_S) -> None:
        super().__init__(f"replay_camera:{seq.path.name}")
        self.seq = seq
        self.schedule = schedule or (np.arange(len(seq)), seq.frame_times_s)
        self.clock = clock
        self.delivery_s = delivery_s
        self.handover_wait_s = handover_wait_s
        self.camera = camera or seq.camera  # as frames are delivered (see delivered_camera)
        self.slot = FrameSlot()
        self.published = 0
        self.unreadable = 0
        self.late = 0  # frames skipped because the next one was already due (see _run)
        self.decode_lead = DecodeLead()

    def start(self) -> None:
        self.clock.start()
        super().start()

    def wait_camera(self, timeout_s: float) -> CameraModel | None:
        return self.camera

    def take(self, after_seq: int = 0, timeout_s: float = 0.0) -> tuple[int, RgbdFrame] | None:
        return self.slot.take(after_seq, timeout_s)

    @property
    def exhausted(self) -> bool:
        return self.slot.closed

    def _run(self) -> None:
        index, played = self.schedule
        n = len(index)
        try:
            for k in range(n):
                i, t_play = index[k], played[k]
                # A camera captures on its own clock whatever its reader does.
                # When decoding falls behind (a busy CPU) and the next frame is
                # already due, this one would be replaced in the slot at once:
                # skip it, as a camera's slot would drop it, rather than lag
                # the clock for good (the attitude, played on time, would then
                # run out of the buffer around the frames: "no attitude").
                if k + 1 < n and self.clock.now_s() >= played[k + 1] + self.delivery_s:
                    if self.late == 0:
                        log.warning("%s: decoding behind the replay clock; skipping frames "
                                    "that are already stale (counted as late)", self.name)
                    self.late += 1
                    continue
                lead_s = self.decode_lead.lead_s * self.clock.speed  # in recording time
                if not self.clock.wait_until(t_play + self.delivery_s - lead_s, self._stop):
                    return
                t0 = time.monotonic()
                frame = self.seq.read_frame(int(i))  # decode just before it is due
                self.decode_lead.add(time.monotonic() - t0)
                if frame is None:
                    self.unreadable += 1
                    continue
                if frame.t_s != t_play:
                    frame = played_frame(frame, float(t_play), pass_direction(index, k))
                if not self.clock.wait_until(frame.t_s + self.delivery_s, self._stop):
                    return
                seq = self.slot.put(frame)
                self.published += 1
                # A camera's driver thread sleeps once it has handed a frame
                # over (the OAK's waits on its device queue). Decoding the next
                # one at once kept this core busy as the loop woke, so the loop
                # woke on the other, idle one: on the 2-core VM 24-44 of 900
                # frames reached it 2-10 ms late (docs/latency.md, "Priority").
                self.slot.wait_taken(seq, self.handover_wait_s)
        finally:
            self.slot.close()


class ReplayAttitude(DriverThread):
    """Attitude samples (t_s, q_W_B_xyzw) pushed into `sink` at their stamps."""

    def __init__(self, t_s: np.ndarray, q_W_B_xyzw: np.ndarray, clock: ReplayClock,
                 sink: Callable[[AttitudeSample], object], name: str = "replay_attitude") -> None:
        super().__init__(name)
        self.t_s = np.asarray(t_s, dtype=np.float64)
        self.q_W_B_xyzw = np.asarray(q_W_B_xyzw, dtype=np.float64).reshape(-1, 4)
        self.clock = clock
        self.sink = sink
        self.published = 0
        self.finished = threading.Event()

    def start(self) -> None:
        self.clock.start()
        super().start()

    def _run(self) -> None:
        try:
            for t, q in zip(self.t_s, self.q_W_B_xyzw):
                if not self.clock.wait_until(float(t), self._stop):
                    return
                self.sink(AttitudeSample(int(round(float(t) * 1e9)),
                                         (float(q[0]), float(q[1]), float(q[2]), float(q[3]))))
                self.published += 1
        finally:
            self.finished.set()


def delivered_camera(camera: CameraModel, undistort: bool) -> CameraModel:
    """The reader undistorts onto the same K: frames then have no distortion."""
    if not (undistort and camera.is_distorted):
        return camera
    return CameraModel(camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height,
                       camera.depth_scale, (), camera.q_B_C_xyzw)


@dataclass
class Replay:
    """A sequence's replay drivers on one clock; start() and stop() both."""

    seq: Sequence
    clock: ReplayClock
    camera: ReplayCamera
    attitude: ReplayAttitude | None
    buffer: AttitudeBuffer
    attitude_label: str
    passes: int = 1  # forwards/backwards passes (loop_s)
    stop_times_s: dict[str, float] = field(default_factory=dict)

    def start(self) -> None:
        self.clock.start()
        if self.attitude is not None:
            self.attitude.start()
        self.camera.start()

    def stop(self, timeout_s: float = 5.0) -> bool:
        """Stop both; `stop_times_s` records each join, as onboard.app.hardware.Hardware."""
        ok = True
        for t in (self.camera, self.attitude):
            if t is not None:
                ok = t.stop(timeout_s) and ok
                self.stop_times_s[t.name] = t.last_stop_s or 0.0
        return ok


def open_replay(
    seq_dir: Path | str,
    *,
    speed: float = 1.0,
    buffer_capacity: int = 1024,
    max_gap_s: float = 0.2,
    assoc_max_dt_s: float = 0.02,
    undistort: bool = True,
    stamp_window_s: float = DEFAULT_WINDOW_S,
    mono_ns: Callable[[], int] = time.monotonic_ns,
    loop_s: float | None = None,
    attitude_smoothing_s: float = DEFAULT_HALF_S,
    attitude_smoothing_max_s: float = DEFAULT_MAX_HALF_S,
    ahrs_noise_deg: float = 0.0,
) -> Replay:
    """Replay drivers for a TUM-layout sequence; attitude within PREROLL_S
    before the first frame to TAIL_S after the last is played. With `loop_s`:
    forwards and backwards in turn (pingpong_schedule) for at least that long
    at `speed`, frames and attitude mirrored alike."""
    seq = open_sequence(seq_dir, assoc_max_dt_s, undistort, stamp_window_s)
    t_first, t_last = float(seq.frame_times_s[0]), float(seq.frame_times_s[-1])
    passes = 1
    if loop_s is not None:
        passes = int(math.ceil(loop_s * speed / max(t_last - t_first, 1.0))) + 1
    # Mirrored passes turn half a frame interval beyond the first and last
    # frames, so attitude brackets every frame at the turns too.
    half_s = 0.5 * float(np.median(np.diff(seq.frame_times_s))) if len(seq) > 1 else 0.017
    span = (t_first - half_s, t_last + half_s)
    clock = ReplayClock(t_first - PREROLL_S, speed, mono_ns)
    if seq.attitude is not None:
        traj, label = seq.attitude, "attitude.txt"
        R_B_C = quat_to_matrix(tuple(seq.camera.q_B_C_xyzw))
    elif seq.groundtruth is not None:
        traj, label = seq.groundtruth, "groundtruth.txt (camera orientation, mount identity)"
        R_B_C = np.eye(3)
    else:
        traj, label, R_B_C = None, "none", quat_to_matrix(tuple(seq.camera.q_B_C_xyzw))
    buffer = AttitudeBuffer(R_B_C, buffer_capacity, max_gap_s, smoothing_s=attitude_smoothing_s,
                            smoothing_max_s=attitude_smoothing_max_s,
                            noise_sd_deg=recorded_noise_deg(seq, ahrs_noise_deg))
    attitude = None
    if traj is not None:
        keep = (traj.t_s >= t_first - PREROLL_S) & (traj.t_s <= t_last + TAIL_S)
        if not keep.any():
            raise NislamError(f"{seq.path}: {label} has no sample near the frames")
        t_att, q_att = traj.t_s[keep], traj.q_xyzw[keep]
        if passes > 1:  # mirrored like the frames: the same map from recording to played time
            i_att, t_att = pingpong_schedule(t_att, passes, span, 0.0)
            q_att = q_att[i_att]
        attitude = ReplayAttitude(t_att, q_att, clock, buffer.push)
    schedule = pingpong_schedule(seq.frame_times_s, passes, span, 0.0) if passes > 1 else None
    camera = ReplayCamera(seq, clock, delivered_camera(seq.camera, undistort), schedule=schedule)
    return Replay(seq, clock, camera, attitude, buffer, label, passes)
