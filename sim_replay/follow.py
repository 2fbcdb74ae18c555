"""Closed-loop synthetic sensors: the RGB-D camera and the AHRS rendered in
real time from a simulated vehicle's true state (`nislam run --sim-follow`).

The simulator (ArduPilot SITL) flies on our poses; its true state arrives
over MAVLink (sim_replay.follow_state: placed in the scene, smoothed,
predicted to any time), and:

- `FollowCamera` (a `CameraSource`) renders the scene from the body pose at
  each capture time of a `camera_hz` grid on the host's monotonic clock,
  applies the depth and colour sensor models of `nislam sim` and puts the
  frame (stamped with its capture time) into a newest-frame slot, where the
  service takes it like an OAK-D frame. A capture time that passed while
  the machine was busy is still rendered (late) up to `LATE_PERIODS`, later
  ones are skipped (counted as late), as a camera drops what nobody reads.
  The camera's true pose at every frame is kept: the ground truth the
  service scores against.
- `FollowAhrs` samples the body attitude at `ahrs_hz` with the AHRS error
  model of the chosen profile (white noise, bias random walk, delay,
  dropouts; sim_replay.sensors) and pushes it into the attitude buffer.

`open_follow()` builds both on one `VehicleTrack`; the application feeds the
track from the MAVLink link (onboard/app/sources.py).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from onboard import NislamError
from onboard.core.attitude import AttitudeSample
from onboard.core.camera import CameraModel
from onboard.core.messages import RgbdFrame
from onboard.core.rotations import matrix_to_quat
from onboard.core.sources import DriverThread, FrameSlot
from onboard.core.trajectory import Trajectory
from sim_replay.attitude import AttitudeErrorModel
from sim_replay.flights import SCENARIOS, Flight, scenario
from sim_replay.follow_render import RenderProcess, RenderSpec, prepare_textures
from sim_replay.follow_state import VehicleTrack
from sim_replay.render import Renderer
from sim_replay.scene import SCENES, make_scene
from sim_replay.sensors import (
    AhrsModel,
    ColourNoise,
    DepthSensorModel,
    ahrs_profile,
    measure_depth,
)
from sim_replay.sim import FOCAL_PER_WIDTH

log = logging.getLogger(__name__)

# A scene's start: where its first flight of `nislam sim` starts.
SCENE_START_FLIGHT = {"room": "circle", "corridor": "corridor"}
DEPTH_SCALE = 5000.0  # as the synthetic recordings (only the camera model carries it)
LATE_PERIODS = 3  # capture times up to this many periods past are still rendered (a queue of 3)
CATCH_UP_S = 1.0  # AHRS samples up to this far past are still sent after a stall


def start_of(name: str, height_m: float) -> tuple[str, str, np.ndarray]:
    """(scene, flight, start point in W): a scene name starts where its first
    flight starts (room: `circle`, corridor: `corridor`), a flight name where
    that flight starts; `height_m` above the floor (z = 0, z down)."""
    if name in SCENE_START_FLIGHT:
        flight = SCENE_START_FLIGHT[name]
    elif name in SCENARIOS:
        flight = name
    else:
        known = sorted(set(SCENE_START_FLIGHT) | set(SCENARIOS))
        raise NislamError(f"--sim-follow: unknown scene or flight {name!r} "
                          f"(known: {', '.join(known)})")
    scen = scenario(flight)
    if scen.scene not in SCENES:
        raise NislamError(f"--sim-follow: flight {flight!r} has no scene")
    p, _ = Flight(scen).body_pose([0.0])
    return scen.scene, flight, np.array([p[0][0], p[0][1], -height_m])


def follow_camera_model(width: int, height: int, q_B_C_xyzw: tuple[float, ...]) -> CameraModel:
    f = FOCAL_PER_WIDTH * width
    return CameraModel(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height,
                       DEPTH_SCALE, (), tuple(q_B_C_xyzw))


@dataclass
class FollowStats:
    frames: int = 0
    late: int = 0  # capture times skipped: rendering was a period or more behind
    no_state: int = 0  # capture times without a fresh vehicle state
    render_ms: list[float] = field(default_factory=list)  # CPU of render + sensor models
    delivery_ms: list[float] = field(default_factory=list)  # capture time -> in the slot


class FollowCamera(DriverThread):
    """The rendered RGB-D camera; a `onboard.core.sources.CameraSource`."""

    def __init__(self, track: VehicleTrack, scene_name: str, camera: CameraModel,
                 R_B_C: np.ndarray, hz: float = 30.0, seed: int = 0,
                 depth: DepthSensorModel | None = None, pixel_noise_dn: float = 2.0,
                 texture_cache: Path | None = None, separate_process: bool = False,
                 clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        super().__init__(f"follow_camera:{scene_name}")
        self.track = track
        self.camera = camera
        self.R_B_C = np.asarray(R_B_C, dtype=np.float64)
        self.period_ns = int(round(1e9 / hz))
        self.depth = depth or DepthSensorModel()
        self.renderer: Renderer | None = None
        self._proc: RenderProcess | None = None
        if separate_process:  # the world's renderer off the tracker's core and GIL
            d = self.depth
            self._proc = RenderProcess(RenderSpec(
                scene_name, camera.width, camera.height, camera.fx, camera.fy, camera.cx,
                camera.cy, seed, None if texture_cache is None else str(texture_cache),
                d.sigma_m_per_m2, d.min_range_m, d.max_range_m, d.edge_rel, d.edge_width_px,
                d.dropout, pixel_noise_dn))
        else:
            self.renderer = Renderer(make_scene(scene_name), camera.intrinsics(), seed=seed)
            prepare_textures(self.renderer, texture_cache)  # every texture now, not mid-flight
            self.noise = ColourNoise((camera.height, camera.width), pixel_noise_dn, seed)
        self.seed = seed
        self.clock_ns = clock_ns
        self.slot = FrameSlot()
        self.stats = FollowStats()
        self._truth_lock = threading.Lock()
        self._truth: list[tuple[float, np.ndarray, np.ndarray]] = []

    def stop(self, timeout_s: float = 5.0) -> bool:
        ended = super().stop(timeout_s)
        if self._proc is not None and ended:
            self._proc.close()
            self._proc = None
        return ended

    # -- CameraSource
    def wait_camera(self, timeout_s: float) -> CameraModel | None:
        return self.camera

    def take(self, after_seq: int = 0, timeout_s: float = 0.0) -> tuple[int, RgbdFrame] | None:
        return self.slot.take(after_seq, timeout_s)

    @property
    def exhausted(self) -> bool:
        return False  # the simulator decides when the flight ends

    @property
    def late(self) -> int:
        return self.stats.late

    def truth(self) -> Trajectory:
        """The camera's true pose (R_W_C, p_W) at every frame rendered."""
        with self._truth_lock:
            rows = list(self._truth)
        if not rows:
            return Trajectory(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4)))
        t = np.array([r[0] for r in rows])
        return Trajectory(t, np.stack([r[1] for r in rows]), np.stack([r[2] for r in rows]))

    # -- thread
    def _run(self) -> None:
        while not self.track.first.wait(0.1):
            if self.stopping:
                return
        t_next = self.clock_ns()
        k = 0
        while not self.stopping:
            now = self.clock_ns()
            if now < t_next and self._sleep((t_next - now) * 1e-9):
                return
            now = self.clock_ns()
            # A capture time already passed is rendered late (its state is
            # known: the track keeps the history), as a camera delivers a frame
            # late when its host stalls; one more than LATE_PERIODS behind is
            # dropped, as a camera's queue drops what nobody reads.
            behind = (now - t_next) // self.period_ns - (LATE_PERIODS - 1)
            if behind > 0:
                self.stats.late += int(behind)
                t_next += int(behind) * self.period_ns
            self._capture(t_next, k)
            k += 1
            t_next += self.period_ns

    def _capture(self, t_ns: int, k: int) -> None:
        pose = self.track.pose_at(t_ns)
        if pose is None:
            self.stats.no_state += 1
            return
        R_W_C = pose.R_W_B @ self.R_B_C
        if self._proc is not None:
            bgr, depth_m, ms = self._proc.render(k, R_W_C, pose.p_W_m)
        else:
            assert self.renderer is not None
            t0 = time.thread_time()
            view = self.renderer.render(R_W_C, pose.p_W_m)
            rng = np.random.default_rng([self.seed, 1, k])
            depth_m = measure_depth(view.depth_m, self.depth, rng)
            bgr = self.noise.apply(view.bgr, rng)
            ms = (time.thread_time() - t0) * 1e3
        self.stats.render_ms.append(ms)
        q = np.asarray(matrix_to_quat(R_W_C), dtype=np.float64)
        with self._truth_lock:
            self._truth.append((t_ns * 1e-9, pose.p_W_m.copy(), q))
        self.slot.put(RgbdFrame(t_s=t_ns * 1e-9, bgr=bgr, depth_m=depth_m))
        self.stats.frames += 1
        self.stats.delivery_ms.append((self.clock_ns() - t_ns) * 1e-6)


class FollowAhrs(DriverThread):
    """Attitude samples of the simulated AHRS, pushed into `sink`."""

    def __init__(self, track: VehicleTrack, sink: Callable[[AttitudeSample], object],
                 model: AhrsModel, seed: int = 0,
                 clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        super().__init__("follow_ahrs")
        self.track = track
        self.sink = sink
        self.model = model
        self.period_ns = int(round(1e9 / model.rate_hz))
        self.clock_ns = clock_ns
        self.rng = np.random.default_rng([seed, 3])
        self.published = 0
        self._bias_rad = np.zeros(3)
        self._last_ns: int | None = None

    def _run(self) -> None:
        while not self.track.first.wait(0.1):
            if self.stopping:
                return
        t_next = self.clock_ns()
        while not self.stopping:
            now = self.clock_ns()
            if now < t_next and self._sleep((t_next - now) * 1e-9):
                return
            sample = self._measure(t_next)
            if sample is not None:
                self.sink(sample)
                self.published += 1
            t_next += self.period_ns
            now = self.clock_ns()
            # After a stall every missed sample still comes, late (the track
            # keeps the history), as a serial AHRS's lines wait in the port: a
            # gap would leave the frames in it without attitude. Only a stall
            # beyond the history is skipped.
            if now - t_next > CATCH_UP_S * 1e9:
                t_next = now

    def _measure(self, t_ns: int) -> AttitudeSample | None:
        """The sample stamped `t_ns`: the truth `offset_ms` earlier, times
        the bias random walk and white noise (body frame), or a dropout."""
        e: AttitudeErrorModel = self.model.errors
        pose = self.track.pose_at(t_ns - int(round(e.offset_ms * 1e6)))
        noise = self.rng.standard_normal(3) * math.radians(e.noise_deg)
        step = self.rng.standard_normal(3)
        drop = self.model.dropout > 0 and self.rng.random() < self.model.dropout
        if self._last_ns is not None and e.bias_deg_per_sqrt_s > 0:
            dt = max(0.0, (t_ns - self._last_ns) * 1e-9)
            self._bias_rad += step * math.radians(e.bias_deg_per_sqrt_s) * math.sqrt(dt)
        self._last_ns = t_ns
        if pose is None or drop:
            return None
        r = (Rotation.from_matrix(pose.R_W_B) * Rotation.from_rotvec(self._bias_rad)
             * Rotation.from_rotvec(noise))
        x, y, z, w = r.as_quat()
        return AttitudeSample(t_ns, (float(x), float(y), float(z), float(w)))


@dataclass
class FollowSkipped:
    """What `metrics.json` reports as skipped inputs (the service asks)."""

    camera: FollowCamera

    def as_dict(self) -> dict[str, int]:
        s = self.camera.stats
        return {"late_frames": s.late, "frames_without_vehicle_state": s.no_state}


class FollowTruth:
    """Ground truth for the service's final score, like a recording's."""

    def __init__(self, camera: FollowCamera) -> None:
        self.camera = camera
        self.skipped = FollowSkipped(camera)

    @property
    def groundtruth(self) -> Trajectory:
        return self.camera.truth()


@dataclass
class Follow:
    """The closed-loop sensors of one simulated vehicle."""

    scene: str
    flight: str
    start_W_m: np.ndarray
    track: VehicleTrack
    camera: FollowCamera
    ahrs: FollowAhrs
    truth: FollowTruth
    label: str

    def stats(self) -> dict[str, object]:
        """For metrics.json: the simulator's states and the rendered frames."""
        s, tr = self.camera.stats, self.track

        def pct(v: list[float], q: float) -> float | None:
            return float(np.percentile(v, q)) if v else None

        return {
            "vehicle_states": tr.states, "vehicle_states_rejected": tr.rejected,
            "frames_rendered": s.frames, "late_frames": s.late,
            "frames_without_vehicle_state": s.no_state,
            "render_ms_median": pct(s.render_ms, 50), "render_ms_p95": pct(s.render_ms, 95),
            # capture time -> the frame in the service's slot (rendering included)
            "delivery_ms_median": pct(s.delivery_ms, 50), "delivery_ms_p99": pct(s.delivery_ms, 99),
            "ahrs_samples": self.ahrs.published,
        }


def open_follow(name: str, *, R_B_C: np.ndarray, q_B_C_xyzw: tuple[float, ...],
                sink: Callable[[AttitudeSample], object], width: int = 640, height: int = 480,
                camera_hz: float = 30.0, ahrs_profile_name: str = "perfect",
                ahrs_hz: float = 100.0, start_height_m: float = 0.1,
                position_tau_s: float = 0.5, seed: int = 0,
                anchor_file: Path | None = None, texture_cache: Path | None = None,
                render_process: bool = False) -> Follow:
    """The camera and AHRS of `--sim-follow NAME`, reading one `VehicleTrack`
    (feed it with `track.push_message(msg, t_ns)`)."""
    scene, flight, start = start_of(name, start_height_m)
    track = VehicleTrack(start, position_tau_s, anchor_file)
    cam_model = follow_camera_model(width, height, q_B_C_xyzw)
    camera = FollowCamera(track, scene, cam_model, R_B_C, camera_hz, seed,
                          texture_cache=texture_cache, separate_process=render_process)
    prof = ahrs_profile(ahrs_profile_name)
    errors = AttitudeErrorModel(prof["noise_deg"], prof["bias_deg_per_sqrt_s"],
                                prof["offset_ms"], seed=seed)
    ahrs = FollowAhrs(track, sink, AhrsModel(ahrs_hz, errors, prof["dropout"]), seed)
    label = (f"sim-follow {scene} (start of {flight}: x {start[0]:.2f} y {start[1]:.2f} "
             f"z {start[2]:.2f} m), {width}x{height} at {camera_hz:g} Hz")
    return Follow(scene, flight, start, track, camera, ahrs, FollowTruth(camera), label)
