"""`nislam record`: live (or replayed) sensor data into the sequence layout.

Writes `rgb/` and `depth/` (PNG, depth 16-bit in the camera's depth units),
`rgb.txt`, `depth.txt`, `attitude.txt` (`t qx qy qz qw`, the body in the AHRS
world) and `camera.toml` (intrinsics of the delivered frames, depth scale,
mount). Crash safety, so that a killed recorder leaves a readable sequence:
- every image and camera.toml is written whole: a temporary name in the same
  folder, then os.replace (atomic on POSIX);
- a frame's list lines are appended only after both of its images are in
  place, each line with one write(2) on an O_APPEND descriptor, so the lists
  never name a missing or partial file and never hold half a line;
- attitude lines are appended the same way, whole lines per write.
Leftover `*.tmp` files of an interrupted write are never listed.

Frames come from a CameraSource's newest-frame slot; a writer thread encodes
them behind a bounded queue (the oldest dropped when full, counted) so the
loop keeps up with the camera. On a replay, the frames the replay camera
skipped as already stale are counted too (`frames_late_at_source`).
Attitude samples come from the attitude buffer (`samples_after`), all of
them, at their own stamps.
"""

from __future__ import annotations

import collections
import logging
import math
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from onboard import NislamError
from onboard.core.attitude import AttitudeBuffer, AttitudeSample
from onboard.core.messages import RgbdFrame

if TYPE_CHECKING:
    from onboard.app.config import Config
    from onboard.app.hardware import Hardware
    from onboard.core.camera import CameraModel
    from sim_replay.sources import ReplayCamera

log = logging.getLogger(__name__)

POLL_S = 0.1  # longest wait for a frame per loop turn (bounds the stop time)
TAIL_S = 0.3  # after a camera's last frame, keep collecting attitude this long
REPLAY_TAIL_TIMEOUT_S = 10.0  # ... or until the attitude replay has played out (at speed 1)


# --------------------------------------------------------------------------- files


def write_whole(path: Path, data: bytes) -> None:
    """Write `data` to `path` via a temporary name and an atomic rename."""
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def check_out_dir(out_dir: Path) -> None:
    """A recording never appends to another one."""
    if (Path(out_dir) / "rgb.txt").exists():
        raise NislamError(f"{out_dir} already holds a recording (rgb.txt); "
                          "choose an empty or new --out folder")


class SequenceWriter:
    """The sequence folder, written incrementally and crash-safely."""

    def __init__(self, out_dir: Path | str, png_compression: int = 1) -> None:
        self.out_dir = Path(out_dir)
        check_out_dir(self.out_dir)
        (self.out_dir / "rgb").mkdir(parents=True, exist_ok=True)
        (self.out_dir / "depth").mkdir(exist_ok=True)
        self.png_params = [cv2.IMWRITE_PNG_COMPRESSION, int(png_compression)]
        self._fds: dict[str, int] = {}
        for name, header in (("rgb.txt", "# colour images\n# timestamp filename\n"),
                             ("depth.txt", "# depth images\n# timestamp filename\n"),
                             ("attitude.txt", "# attitude: body in the AHRS world\n"
                                              "# timestamp qx qy qz qw\n")):
            fd = os.open(self.out_dir / name, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            self._fds[name] = fd
            os.write(fd, header.encode())
        self.frames = 0
        self.attitude_samples = 0
        self._last_frame_t: float = -math.inf
        self._last_att_ns: int | None = None

    def write_camera(self, cam: CameraModel) -> None:
        """camera.toml (flat TOML, as sim_replay.tum.load_camera reads it)."""
        lines = ["# camera of the recorded frames (written by nislam record)"]
        for key in ("fx", "fy", "cx", "cy", "width", "height", "depth_scale"):
            lines.append(f"{key} = {getattr(cam, key)!r}")
        if cam.distortion:
            lines.append(f"distortion = [{', '.join(repr(float(c)) for c in cam.distortion)}]")
        lines.append(f"q_B_C_xyzw = [{', '.join(repr(float(c)) for c in cam.q_B_C_xyzw)}]")
        write_whole(self.out_dir / "camera.toml", ("\n".join(lines) + "\n").encode())

    def write_frame(self, frame: RgbdFrame, depth_scale: float) -> bool:
        """Both images, then their list lines; False for a stale stamp."""
        if not frame.t_s > self._last_frame_t:
            return False
        stamp = f"{frame.t_s:.6f}"
        name = f"{stamp}.png"
        raw = np.clip(np.rint(frame.depth_m * np.float32(depth_scale)), 0, 65535).astype(np.uint16)
        for folder, image in (("rgb", frame.bgr), ("depth", raw)):
            ok, png = cv2.imencode(".png", image, self.png_params)
            if not ok:
                raise NislamError(f"cannot encode {folder}/{name}")
            write_whole(self.out_dir / folder / name, png.tobytes())
        os.write(self._fds["depth.txt"], f"{stamp} depth/{name}\n".encode())
        os.write(self._fds["rgb.txt"], f"{stamp} rgb/{name}\n".encode())
        self._last_frame_t = frame.t_s
        self.frames += 1
        return True

    def write_attitude(self, samples: list[AttitudeSample]) -> None:
        lines = []
        for s in samples:
            if self._last_att_ns is not None and s.t_ns <= self._last_att_ns:
                continue
            q = s.q_W_B_xyzw
            lines.append(f"{s.t_ns * 1e-9:.6f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n")
            self._last_att_ns = s.t_ns
        if lines:
            os.write(self._fds["attitude.txt"], "".join(lines).encode())
            self.attitude_samples += len(lines)

    @property
    def last_attitude_ns(self) -> int | None:
        return self._last_att_ns

    def close(self) -> None:
        for fd in self._fds.values():
            os.close(fd)
        self._fds.clear()


class FrameWriterThread:
    """Encodes and writes frames behind a bounded drop-oldest queue."""

    def __init__(self, writer: SequenceWriter, depth_scale: float, queue_frames: int) -> None:
        self.writer = writer
        self.depth_scale = depth_scale
        self.queue: collections.deque[RgbdFrame] = collections.deque()
        self.max_queue = max(1, queue_frames)
        self.dropped = 0
        self.error: BaseException | None = None
        self._cond = threading.Condition()
        self._finish = False
        self._thread = threading.Thread(target=self._run, name="record_writer", daemon=True)
        self._thread.start()

    def put(self, frame: RgbdFrame) -> None:
        with self._cond:
            if len(self.queue) >= self.max_queue:
                self.queue.popleft()
                self.dropped += 1
            self.queue.append(frame)
            self._cond.notify()

    def finish(self, timeout_s: float = 30.0) -> bool:
        """Write what is queued, then end; True when done in time."""
        with self._cond:
            self._finish = True
            self._cond.notify()
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self.queue or self._finish)
                if not self.queue:
                    return
                frame = self.queue.popleft()
            try:
                self.writer.write_frame(frame, self.depth_scale)
            except (OSError, NislamError) as e:  # disk full, folder removed: stop recording
                self.error = e
                log.error("recording stopped: %s", e)
                with self._cond:
                    self.queue.clear()
                return


# --------------------------------------------------------------------------- record


@dataclass
class RecordResult:
    """What a recording holds and what it lost: on a whole replay every source
    frame is recorded, dropped or late at the source (nothing lost silently)."""

    out_dir: Path
    source: str
    attitude_source: str
    frames: int = 0
    attitude_samples: int = 0
    frames_dropped: int = 0  # newest-frame slot drops + writer queue drops
    frames_late_at_source: int = 0  # replay frames skipped as already stale (ReplayCamera.late)
    seconds: float = 0.0
    stop_times_s: dict[str, float] = field(default_factory=dict)

    def summary_lines(self) -> list[str]:
        hz = self.frames / self.seconds if self.seconds > 0 else 0.0
        stops = ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in self.stop_times_s.items())
        return [
            f"recorded {self.frames} frames ({hz:.1f} Hz) and {self.attitude_samples} attitude "
            f"samples in {self.seconds:.1f} s into {self.out_dir}",
            f"source: {self.source}; attitude: {self.attitude_source}; "
            f"frames dropped: {self.frames_dropped}; "
            f"late at the source: {self.frames_late_at_source}",
            f"driver stop times: {stops or 'n/a'}",
        ]


def record(
    cfg: Config,
    out_dir: Path | str,
    *,
    seconds: float | None = None,
    replay_dir: Path | str | None = None,
    replay_speed: float = 1.0,
    stop: threading.Event | None = None,
    hardware: Hardware | None = None,
) -> RecordResult:
    """Record until `seconds` pass, `stop` is set, or the replay ends.

    Sources: the replay drivers for `replay_dir`, played at `replay_speed`
    (1 = real time; slower leaves a busy machine more time per frame); else
    `hardware` (built by onboard.app.hardware.make_hardware from `cfg` when None)."""
    stop = stop or threading.Event()
    out_dir = Path(out_dir)
    replay_camera: ReplayCamera | None = None  # counts the frames it skipped as late
    tail_timeout_s = REPLAY_TAIL_TIMEOUT_S
    if replay_dir is not None:
        from sim_replay.sources import open_replay

        rp = open_replay(replay_dir, speed=replay_speed, buffer_capacity=cfg.ahrs.buffer_samples,
                         max_gap_s=cfg.ahrs.max_gap_s, attitude_smoothing_s=cfg.ahrs.smoothing_s,
                         attitude_smoothing_max_s=cfg.ahrs.smoothing_max_s,
                         ahrs_noise_deg=cfg.nislam.attitude_sd_deg,
                         assoc_max_dt_s=cfg.replay.assoc_max_dt_s, undistort=cfg.replay.undistort)
        camera, buffer, sources = rp.camera, rp.buffer, rp
        result = RecordResult(out_dir, f"replay of {Path(replay_dir)}", rp.attitude_label)
        attitude_done = rp.attitude.finished if rp.attitude is not None else None
        replay_camera = rp.camera
        tail_timeout_s = REPLAY_TAIL_TIMEOUT_S / min(1.0, replay_speed)
    else:
        from onboard.app.hardware import make_hardware

        hw = hardware or make_hardware(cfg, camera=True)
        if hw.camera is None:
            raise NislamError("recording needs a camera")
        camera, buffer, sources = hw.camera, hw.buffer, hw
        result = RecordResult(out_dir, "OAK-D", hw.attitude_label)
        attitude_done = None
    check_out_dir(out_dir)  # before any device opens
    writer: SequenceWriter | None = None
    frame_writer: FrameWriterThread | None = None
    t0 = time.monotonic()
    sources.start()
    try:
        cam = camera.wait_camera(cfg.record.start_timeout_s)
        if cam is None:
            raise NislamError(f"camera not streaming after {cfg.record.start_timeout_s:g} s")
        writer = SequenceWriter(out_dir, cfg.record.png_compression)  # the camera is up
        writer.write_camera(cam)
        frame_writer = FrameWriterThread(writer, cam.depth_scale, cfg.record.queue_frames)
        _loop(camera, buffer, writer, frame_writer, stop,
              None if seconds is None else t0 + seconds, attitude_done, tail_timeout_s)
    finally:
        sources.stop()
        result.stop_times_s = dict(sources.stop_times_s)
        if frame_writer is not None:
            frame_writer.finish()
            result.frames_dropped += frame_writer.dropped
        if writer is not None:
            writer.write_attitude(buffer.samples_after(writer.last_attitude_ns))
            writer.close()
    if frame_writer is not None and frame_writer.error is not None:
        raise NislamError(f"recording failed: {frame_writer.error}")
    result.frames = writer.frames
    result.attitude_samples = writer.attitude_samples
    result.frames_dropped += camera.slot.stats.dropped
    result.frames_late_at_source = replay_camera.late if replay_camera is not None else 0
    result.seconds = time.monotonic() - t0
    return result


def _loop(camera: Any, buffer: AttitudeBuffer, writer: SequenceWriter,
          frame_writer: FrameWriterThread, stop: threading.Event, deadline: float | None,
          attitude_done: threading.Event | None, tail_timeout_s: float) -> None:
    last_seq = 0
    tail_until: float | None = None
    while not stop.is_set() and frame_writer.error is None:
        now = time.monotonic()
        if deadline is not None and now >= deadline:
            break
        # Read before the take: a frame put just before the camera closed is
        # then still taken, not left in the slot uncounted.
        exhausted = camera.exhausted
        got = camera.take(last_seq, POLL_S)
        if got is not None:
            last_seq, frame = got
            frame_writer.put(frame)
        writer.write_attitude(buffer.samples_after(writer.last_attitude_ns))
        if got is None and exhausted:
            # End of a replay: collect the attitude that follows the last frame.
            if attitude_done is not None:
                attitude_done.wait(tail_timeout_s)
                break
            tail_until = tail_until or now + TAIL_S
            if now >= tail_until:
                break
