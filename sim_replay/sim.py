"""`nislam sim` as a function: fly a named scenario through a synthetic scene
and write the recording in the TUM layout the reader takes.

Written into the output folder:
  rgb/, depth/        colour PNG and 16-bit depth PNG per frame (depth_scale units per m)
  rgb.txt, depth.txt  `timestamp file` lists (colour and depth share their stamps)
  groundtruth.txt     exact camera pose T_W_C per frame (`t tx ty tz qx qy qz qw`)
  attitude.txt        AHRS samples `t qx qy qz qw` (body in W) at the AHRS rate
  camera.toml         intrinsics, depth_scale, q_B_C_xyzw (the mount)
  sim.json            what was simulated: scenario, seed, models, render speed
Only these are (over)written, and a folder holding a recording that `nislam
sim` or `nislam faults` did not write is refused (sim_replay.outdir).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
import tempfile
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from onboard import NislamError, __version__
from onboard.core.camera import CameraIntrinsics
from onboard.core.rotations import mount_rotation
from onboard.core.trajectory import write_tum
from sim_replay.attitude import AttitudeErrorModel
from sim_replay.fault_plan import parse_spec
from sim_replay.faults import inject_faults
from sim_replay.flights import Flight, scenario
from sim_replay.outdir import SIM_MANIFEST, finish_out_dir, prepare_out_dir
from sim_replay.render import Renderer
from sim_replay.scene import make_scene
from sim_replay.sensors import (
    PERFECT_DEPTH,
    AhrsModel,
    ColourNoise,
    DepthSensorModel,
    ahrs_profile,
    ahrs_sample_times,
    depth_profile,
    depth_to_png_units,
    measure_attitude,
    measure_depth,
)

FOCAL_PER_WIDTH = 525.0 / 640.0  # 63 deg horizontal field of view (Kinect / OAK-D class)
# PNG level 1 with the SUB filter: a third of the default's encode time at the
# same size (the adaptive filter search is what costs).
_PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1]
if hasattr(cv2, "IMWRITE_PNG_FILTER"):
    _PNG_PARAMS += [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB]


# Bounds on what a user can ask for (a typo must not render for hours or run
# out of memory): 10 minutes is 18 000 frames at 30 Hz, several GB of PNGs.
MAX_SIM_SECONDS = 600.0
MAX_CAMERA_HZ = 120.0
MAX_IMAGE_PX = 4096


@dataclass(frozen=True)
class SimOptions:
    """Everything a synthetic flight depends on besides the scenario name."""

    seconds: float = 20.0
    seed: int = 0
    camera_hz: float = 30.0
    width: int = 640
    height: int = 480
    mount: str = "forward"
    depth_scale: float = 5000.0  # depth PNG units per metre (TUM convention)
    depth: DepthSensorModel = field(default_factory=DepthSensorModel)
    pixel_noise_dn: float = 2.0  # colour noise std, grey levels
    ahrs: AhrsModel = field(default_factory=AhrsModel)
    texel_m: float = 0.003
    t0_s: float = 1000.0  # recording clock at take-off (a monotonic clock, not 0)

    def __post_init__(self) -> None:
        if not 0 < self.seconds <= MAX_SIM_SECONDS:
            raise NislamError(f"a synthetic flight's --seconds must be in (0, {MAX_SIM_SECONDS:g}], "
                              f"got {self.seconds:g}")
        if not 0 < self.camera_hz <= MAX_CAMERA_HZ:
            raise NislamError(f"camera rate must be in (0, {MAX_CAMERA_HZ:g}] Hz, "
                              f"got {self.camera_hz:g}")
        if not (16 <= self.width <= MAX_IMAGE_PX and 16 <= self.height <= MAX_IMAGE_PX):
            raise NislamError(f"image size must be within 16x16 .. {MAX_IMAGE_PX}x{MAX_IMAGE_PX}, "
                              f"got {self.width}x{self.height}")
        if self.seed < 0:
            raise NislamError(f"--seed must be >= 0, got {self.seed}")
        if not 0 < self.depth_scale <= 65535:
            raise NislamError(f"depth_scale must be in (0, 65535], got {self.depth_scale}")
        mount_rotation(self.mount)  # validates the name

    def intrinsics(self) -> CameraIntrinsics:
        f = FOCAL_PER_WIDTH * self.width
        return CameraIntrinsics(f, f, (self.width - 1) / 2.0, (self.height - 1) / 2.0,
                                self.width, self.height)


def sim_options(
    seconds: float = 20.0,
    seed: int = 0,
    camera_hz: float = 30.0,
    ahrs_hz: float = 100.0,
    width: int = 640,
    height: int = 480,
    mount: str = "forward",
    ideal_camera: bool = False,
    ahrs_profile_name: str | None = None,
    attitude_noise_deg: float | None = None,
    attitude_bias_deg_per_sqrt_s: float | None = None,
    attitude_offset_ms: float | None = None,
    attitude_dropout: float | None = None,
    texel_m: float = 0.003,
    depth_profile_name: str | None = None,
) -> SimOptions:
    """SimOptions from command-line values: a named AHRS profile sets the four
    error terms together, explicit values override it, the rest is zero; a
    named depth profile (sensors.DEPTH_PROFILES) picks the depth sensor."""
    if ideal_camera and depth_profile_name:
        raise NislamError("--ideal-camera has exact depth: leave out --depth-profile")
    prof = ahrs_profile(ahrs_profile_name) if ahrs_profile_name else {}

    def pick(value: float | None, key: str) -> float:
        return float(value) if value is not None else float(prof.get(key, 0.0))

    errors = AttitudeErrorModel(
        pick(attitude_noise_deg, "noise_deg"),
        pick(attitude_bias_deg_per_sqrt_s, "bias_deg_per_sqrt_s"),
        pick(attitude_offset_ms, "offset_ms"),
        seed=seed,
    )
    ahrs = AhrsModel(ahrs_hz, errors, pick(attitude_dropout, "dropout"))
    camera: dict[str, Any] = {}
    if ideal_camera:
        camera = {"depth": PERFECT_DEPTH, "pixel_noise_dn": 0.0}
    elif depth_profile_name:
        camera = {"depth": depth_profile(depth_profile_name)}
    return SimOptions(seconds=seconds, seed=seed, camera_hz=camera_hz, width=width,
                      height=height, mount=mount, ahrs=ahrs, texel_m=texel_m, **camera)


@dataclass
class SimResult:
    out_dir: Path
    scenario: str
    frames: int
    attitude_samples: int
    render_ms: list[float]
    wall_s: float
    faults: dict[str, Any] | None = None

    @property
    def render_fps(self) -> float:
        """Frames per second of rendering + sensor models alone (one core)."""
        med = float(np.median(self.render_ms)) if self.render_ms else 0.0
        return 1000.0 / med if med > 0 else 0.0

    def summary_lines(self) -> list[str]:
        ms = np.asarray(self.render_ms)
        lines = [
            f"scenario    {self.scenario}",
            f"frames      {self.frames} colour + depth, {self.attitude_samples} attitude samples",
            f"render      median {np.median(ms):.1f} ms, p95 {np.percentile(ms, 95):.1f} ms "
            f"per frame ({self.render_fps:.0f} frames/s on one core, sensor models included)",
            f"wall time   {self.wall_s:.1f} s (PNG writing included)",
        ]
        if self.faults is not None:
            lines.append(f"faults      {self.faults['spec']}: {_expected_text(self.faults)}")
        lines.append(f"output      {self.out_dir}")
        return lines


def _expected_text(manifest: dict[str, Any]) -> str:
    exp = manifest.get("expected", {})
    return ", ".join(f"{k} +{v}" for k, v in exp.items() if v) or "none"


# --------------------------------------------------------------------------- run


def simulate(
    scenario_name: str,
    out_dir: Path | str,
    opts: SimOptions = SimOptions(),
    faults: str | None = None,
    progress: bool = True,
) -> SimResult:
    """Fly `scenario_name` and write the recording into `out_dir`; with
    `faults` (sim_replay.faults spec) the folder holds the damaged recording."""
    out_dir = Path(out_dir)
    scen = scenario(scenario_name)  # bad names fail before any work
    fault_spec = parse_spec(faults) if faults else None
    prepare_out_dir(out_dir)
    if fault_spec is None:
        result = _simulate_into(scen.name, out_dir, opts, progress)
        finish_out_dir(out_dir)
        return result
    # Render a clean flight beside the output, then write the damaged copy.
    clean = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.clean.", dir=out_dir.parent))
    try:
        result = _simulate_into(scen.name, clean, opts, progress)
        manifest = inject_faults(clean, out_dir, fault_spec, seed=opts.seed)
        shutil.copyfile(clean / SIM_MANIFEST, out_dir / SIM_MANIFEST)
    finally:
        shutil.rmtree(clean, ignore_errors=True)
    result.out_dir = out_dir
    result.faults = manifest
    return result


def _simulate_into(name: str, out_dir: Path, opts: SimOptions, progress: bool) -> SimResult:
    t_wall = time.perf_counter()
    cv2.setNumThreads(1)  # rendering has to fit one core; PNG writers use the others
    scen = scenario(name)
    scene = make_scene(scen.scene)
    flight = Flight(scen)
    intr = opts.intrinsics()
    R_B_C = mount_rotation(opts.mount)
    renderer = Renderer(scene, intr, seed=opts.seed, texel_m=opts.texel_m)
    colour_noise = ColourNoise((opts.height, opts.width), opts.pixel_noise_dn, opts.seed)

    n = max(1, int(round(opts.seconds * opts.camera_hz)))
    # Stamps as written (microseconds); every pose is evaluated at them exactly.
    t_frames = np.round(opts.t0_s + np.arange(n) / opts.camera_hz, 6)
    p_W, R_W_B = flight.body_pose(t_frames - opts.t0_s)
    R_W_C = R_W_B @ R_B_C

    (out_dir / "rgb").mkdir(parents=True, exist_ok=True)
    (out_dir / "depth").mkdir(exist_ok=True)
    render_ms: list[float] = []
    names = [f"{t:.6f}.png" for t in t_frames]
    # One writer thread: PNG encoding (OpenCV releases the GIL) takes about as
    # long as rendering, so on two cores the renderer keeps one to itself.
    with ThreadPoolExecutor(max_workers=1) as pool, tqdm(
        total=n, unit="frame", desc=f"sim {name}", file=sys.stderr,
        disable=None if progress else True,
    ) as bar:
        pending: deque[Future] = deque()
        for k in range(n):
            # CPU time of this thread: the cost on one core, whatever else the
            # machine runs (OpenCV is pinned to this thread above).
            t0 = time.thread_time()
            tex0 = renderer.texture_build_s
            view = renderer.render(R_W_C[k], p_W[k])
            rng = np.random.default_rng([opts.seed, 1, k])
            depth_m = measure_depth(view.depth_m, opts.depth, rng)
            bgr = colour_noise.apply(view.bgr, rng)
            depth_units = depth_to_png_units(depth_m, opts.depth_scale)
            # A surface's texture is built once, the first time it is seen: a
            # start-up cost, not part of the per-frame rendering figure.
            tex_s = renderer.texture_build_s - tex0
            render_ms.append((time.thread_time() - t0 - tex_s) * 1e3)
            pending.append(pool.submit(_write_png, out_dir / "rgb" / names[k], bgr))
            pending.append(pool.submit(_write_png, out_dir / "depth" / names[k], depth_units))
            while len(pending) > 8:  # bound the frames held in memory
                pending.popleft().result()
            bar.update(1)
        for f in pending:
            f.result()

    _write_lists(out_dir, t_frames, names)
    write_tum(out_dir / "groundtruth.txt", t_frames, p_W,
              Rotation.from_matrix(R_W_C).as_quat())
    n_att = _write_attitude(out_dir, flight, opts, t_frames)
    _write_camera(out_dir, intr, opts.depth_scale, R_B_C)
    result = SimResult(out_dir, name, n, n_att, render_ms, time.perf_counter() - t_wall)
    _write_manifest(out_dir, scen.name, scen.description, scene.name, opts, intr, result)
    return result


def _write_png(path: Path, img: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", img, _PNG_PARAMS)
    if not ok:
        raise NislamError(f"cannot encode {path}")
    try:
        path.write_bytes(buf.tobytes())
    except OSError as e:
        raise NislamError(f"cannot write {path}: {e.strerror}") from None


def _write_lists(out_dir: Path, t_frames: np.ndarray, names: list[str]) -> None:
    for stream in ("rgb", "depth"):
        lines = [f"# {stream} images of a synthetic flight (nislam sim)", "# timestamp filename"]
        lines += [f"{t:.6f} {stream}/{nm}" for t, nm in zip(t_frames, names)]
        _write_text(out_dir / f"{stream}.txt", "\n".join(lines) + "\n")


def _write_attitude(out_dir: Path, flight: Flight, opts: SimOptions, t_frames: np.ndarray
                    ) -> int:
    # The AHRS runs on the same clock but its own phase: its samples never
    # coincide with frame stamps, so the replay always interpolates.
    phase_s = float(np.random.default_rng([opts.seed, 2]).uniform(0.0, 1.0 / opts.ahrs.rate_hz))
    t_att = ahrs_sample_times(float(t_frames[0]), float(t_frames[-1]), opts.ahrs.rate_hz, phase_s)
    t_s, q = measure_attitude(
        t_att, lambda t: flight.R_W_B(t - opts.t0_s), opts.ahrs,
        np.random.default_rng([opts.seed, 3]),
    )
    lines = ["# AHRS attitude of a synthetic flight: body (FRD) in W (z down)",
             "# timestamp qx qy qz qw"]
    lines += [f"{t:.6f} {r[0]:.9f} {r[1]:.9f} {r[2]:.9f} {r[3]:.9f}" for t, r in zip(t_s, q)]
    _write_text(out_dir / "attitude.txt", "\n".join(lines) + "\n")
    return len(t_s)


def _write_camera(out_dir: Path, intr: CameraIntrinsics, depth_scale: float, R_B_C: np.ndarray
                  ) -> None:
    q = Rotation.from_matrix(R_B_C).as_quat()
    text = (
        "# synthetic pinhole camera (nislam sim): no distortion\n"
        f"fx = {intr.fx!r}\nfy = {intr.fy!r}\ncx = {intr.cx!r}\ncy = {intr.cy!r}\n"
        f"width = {intr.width}\nheight = {intr.height}\n"
        f"depth_scale = {float(depth_scale)!r}\n"
        f"q_B_C_xyzw = [{q[0]:.12f}, {q[1]:.12f}, {q[2]:.12f}, {q[3]:.12f}]\n"
    )
    _write_text(out_dir / "camera.toml", text)


def _write_manifest(out_dir: Path, name: str, description: str, scene: str, opts: SimOptions,
                    intr: CameraIntrinsics, result: SimResult) -> None:
    ms = np.asarray(result.render_ms)
    manifest = {
        "generator": f"nislam-onboard {__version__} nislam sim",
        "scenario": name,
        "description": description,
        "scene": scene,
        "options": asdict(opts),
        "intrinsics": asdict(intr),
        "frames": result.frames,
        "attitude_samples": result.attitude_samples,
        "render_ms_median": float(np.median(ms)),
        "render_ms_p95": float(np.percentile(ms, 95)),
        "render_fps": result.render_fps,
    }
    _write_text(out_dir / SIM_MANIFEST, json.dumps(manifest, indent=2, default=_json) + "\n")


def _json(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    raise TypeError(f"not JSON-able: {type(v).__name__}")


def _write_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise NislamError(f"cannot write {path}: {e.strerror}") from None
