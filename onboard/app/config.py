"""Typed configuration: defaults in code, overrides from a TOML file and the CLI.

Sections map one-to-one onto frozen dataclasses: `[replay]` -> ReplayConfig,
`[attitude]` -> AttitudeErrorConfig, `[tracker]` -> TrackerConfig,
`[nislam]` / `[fastorb]` -> the trackers' own `NislamParams` / `FastOrbParams`,
`[mavlink]` -> MavlinkConfig
and `[zenoh]` -> ZenohConfig (the outputs); `[ahrs]`, `[myahrs]`,
`[autopilot]`, `[oak]` and `[record]` -> the driver and recording sections
(AhrsConfig ... RecordConfig); `[service]` -> ServiceConfig (`nislam run`).
The `[nislam]` and `[fastorb]` keys are read
from those dataclasses' fields, so a parameter added to a tracker is
configurable (and validated by its type) without touching this module.

Every bad key stops the load with one `NislamError` line naming the key: an
unknown key, a value of the wrong type or one outside its range.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import sys
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import tomli_w

from onboard import NislamError, __version__
from onboard.fastorb import FastOrbParams
from onboard.nislam import NislamParams
from onboard.trackers import TRACKER_NAMES

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - pyproject pulls tomli in for 3.10
    import tomli as tomllib

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReplayConfig:
    """How a recorded sequence is read."""

    assoc_max_dt_s: float = 0.02  # rgb/depth pairing window (TUM associate.py default)
    gt_max_gap_s: float = 0.2  # ground truth / attitude interpolate across gaps up to this
    undistort: bool = True  # undistort colour and depth once with precomputed maps


@dataclass(frozen=True)
class AttitudeErrorConfig:
    """Error added to the replayed attitude (see sim_replay.attitude.AttitudeErrorModel)."""

    noise_deg: float = 0.0
    bias_deg_per_sqrt_s: float = 0.0
    offset_ms: float = 0.0
    seed: int = 0


@dataclass(frozen=True)
class TrackerConfig:
    name: str = "nislam"


MOUNT_NAMES = ("forward", "down", "custom")
WORLD_FRAMES = ("frd", "flu")
MAVLINK_MESSAGES = ("odometry", "vision_position")
ZENOH_MODES = ("peer", "client", "router")


@dataclass(frozen=True)
class MavlinkConfig:
    """The vision-position feed to the flight controller (onboard/mavlink_out.py)."""

    enabled: bool = False
    connect: str = "udpout:127.0.0.1:14550"  # pymavlink connection string
    baud: int = 921600  # serial baud rate unless `connect` names one ("/dev/ttyAMA0,921600")
    system_id: int = 1  # our MAVLink system id: the vehicle's (the autopilot's) id
    component_id: int = 197  # MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY
    message: str = "odometry"  # or "vision_position" (VISION_POSITION/SPEED_ESTIMATE)
    mount: str = "forward"  # camera mount R_B_C: "forward", "down" or "custom"
    mount_q_B_C_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)  # "custom"
    world_frame: str = "frd"  # axes of the tracker world W: "frd" (z down) or "flu" (z up)
    degraded_quality: int = 20  # tracking below this quality is "degraded" (CRITICAL)
    jump_m: float = 0.1  # a step longer than this ...
    jump_speed_m_s: float = 10.0  # ... and faster than this is a jump: reset_counter + 1
    velocity_window_s: float = 0.1  # velocity from poses up to this far apart
    heartbeat_period_s: float = 1.0
    stale_s: float = 0.5  # no tracker result for this long = lost ("no frames")
    reconnect_s: float = 1.0  # retry a link that failed after this long
    queue_frames: int = 8  # results waiting for the sender; the oldest is dropped
    set_origin: bool = False  # send SET_GPS_GLOBAL_ORIGIN and SET_HOME_POSITION at start
    origin_lat_deg: float = 0.0
    origin_lon_deg: float = 0.0
    origin_alt_m: float = 0.0  # above mean sea level


@dataclass(frozen=True)
class ZenohConfig:
    """Pose, status and map publishing (onboard/zenoh_out.py) and `nislam listen`."""

    enabled: bool = False
    vehicle: str = "drone1"  # keys live under nislam/<vehicle>/
    mode: str = "peer"  # zenoh session mode: "peer", "client" or "router"
    connect: tuple[str, ...] = ()  # endpoints to connect to, e.g. "tcp/192.168.1.10:7447"
    listen: tuple[str, ...] = ()  # endpoints to listen on, e.g. "tcp/0.0.0.0:7447"
    multicast_scouting: bool = False  # find peers by UDP multicast (off: explicit endpoints)
    status_period_s: float = 1.0
    queue_frames: int = 32  # poses waiting for the publisher; the oldest is dropped
    map_max_mb: float = 512.0  # key frames kept for late joiners; the oldest go first


# Drivers (drivers/) and `nislam record`. The flight-controller link the
# autopilot attitude source uses is the [mavlink] one (connect, baud,
# system_id = the autopilot's system, reconnect_s): one link per autopilot.
# The camera mount R_B_C is [mavlink] mount / mount_q_B_C_xyzw.
AHRS_SOURCES = ("none", "myahrs", "autopilot", "oak_imu")
OAK_STEREO_PRESETS = ("DEFAULT", "FAST_ACCURACY", "FAST_DENSITY", "HIGH_DETAIL", "ROBOTICS",
                      "DENSITY", "ACCURACY")
OAK_IMU_WORLDS = ("enu", "ned")
_IDENTITY_Q = (0.0, 0.0, 0.0, 1.0)


@dataclass(frozen=True)
class AhrsConfig:
    """Which AHRS feeds the attitude buffer (drivers/attitude.py), and the buffer."""

    source: str = "myahrs"  # "myahrs", "autopilot", "oak_imu" or "none"
    buffer_samples: int = 1024  # samples kept (10 s at 100 Hz)
    max_age_s: float = 0.25  # an AHRS this far behind a frame is not waited for (silent)
    max_gap_s: float = 0.1  # no interpolation across a longer gap between samples


@dataclass(frozen=True)
class MyAhrsConfig:
    """myAHRS+ on a serial port (drivers/myahrs.py)."""

    port: str = "/dev/myahrs"  # a stable udev symlink, not /dev/ttyACMn
    baud: int = 115200
    divider: int = 1  # output rate 100 / divider Hz
    latency_ms: float = 0.0  # subtracted from each sample's arrival stamp
    q_B_A_xyzw: tuple[float, float, float, float] = _IDENTITY_Q  # AHRS axes -> body FRD
    silence_s: float = 1.0  # no sample this long: send the start-up commands again
    reopen_s: float = 3.0  # no sample this long: close and reopen the port
    reconnect_max_s: float = 2.0  # reopen backoff ceiling


@dataclass(frozen=True)
class AutopilotConfig:
    """ATTITUDE_QUATERNION from the autopilot over the [mavlink] link."""

    rate_hz: float = 50.0  # requested with MAV_CMD_SET_MESSAGE_INTERVAL
    target_component: int = 1  # the autopilot's component (0 = any)
    latency_ms: float = 0.0  # autopilot-internal delay, subtracted from mapped stamps
    q_B_A_xyzw: tuple[float, float, float, float] = _IDENTITY_Q  # autopilot body -> body
    retry_s: float = 1.0  # re-request when unanswered or the stream stops this long
    clock_window_s: float = 10.0  # boot-time offset: minimum over this window


@dataclass(frozen=True)
class OakConfig:
    """The OAK-D camera and its IMU (drivers/oak.py)."""

    device: str = ""  # device id (MxId); "" = the first one found
    width: int = 640  # colour output size, depth aligned to it
    height: int = 400
    fps: float = 30.0
    mono_width: int = 640  # stereo pair size
    mono_height: int = 400
    undistort: bool = True  # undistort colour on the device
    stereo_preset: str = "DEFAULT"  # StereoDepth.PresetMode name
    imu_rate_hz: int = 100  # rotation vector rate (ahrs.source = "oak_imu")
    imu_world: str = "enu"  # axes of the rotation vector's world (BNO08x: East-North-Up)
    imu_q_B_A_xyzw: tuple[float, float, float, float] = _IDENTITY_Q  # IMU axes -> body FRD
    search_s: float = 3.0  # device search per attempt
    frame_timeout_s: float = 2.0  # no frame this long = device lost, reconnect
    reconnect_max_s: float = 5.0  # reconnect backoff ceiling


@dataclass(frozen=True)
class RecordConfig:
    """`nislam record` (drivers/recorder.py)."""

    png_compression: int = 1  # 0-9: PNG zlib level (1 keeps up with 30 Hz on one core)
    queue_frames: int = 30  # frames waiting for the writer thread; when full the oldest is dropped
    start_timeout_s: float = 30.0  # give up when the camera is not up by then


@dataclass(frozen=True)
class ServiceConfig:
    """`nislam run`, the onboard loop (onboard/service.py)."""

    fallback_tracker: str = ""  # tracker while the attitude is missing ("" none, "fastorb")
    return_after_s: float = 1.0  # attitude back this long: hand back to the primary tracker
    frame_timeout_s: float = 0.5  # no frame for this long: lost ("no frames")
    degraded_gap_s: float = 0.2  # a gap between frames longer than this: degraded
    start_grace_s: float = 10.0  # "starting" this long without a frame, then lost
    recover_s: float = 1.0  # degraded or lost: back to tracking only after this long without problems
    poll_s: float = 0.05  # longest wait for a frame per loop turn (watchdog and stop latency)
    attitude_wait_s: float = 0.05  # longest wait for the AHRS to reach a frame's capture time
    stats_period_s: float = 5.0  # one statistics line (and systemd STATUS) this often
    replay_speed: float = 1.0  # --replay / --sim pace: 1 = real time


@dataclass(frozen=True)
class Config:
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    attitude: AttitudeErrorConfig = field(default_factory=AttitudeErrorConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    nislam: NislamParams = field(default_factory=NislamParams)
    fastorb: FastOrbParams = field(default_factory=FastOrbParams)
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    ahrs: AhrsConfig = field(default_factory=AhrsConfig)
    myahrs: MyAhrsConfig = field(default_factory=MyAhrsConfig)
    autopilot: AutopilotConfig = field(default_factory=AutopilotConfig)
    oak: OakConfig = field(default_factory=OakConfig)
    record: RecordConfig = field(default_factory=RecordConfig)
    service: ServiceConfig = field(default_factory=ServiceConfig)


SECTIONS: dict[str, type] = {
    "replay": ReplayConfig,
    "attitude": AttitudeErrorConfig,
    "tracker": TrackerConfig,
    "nislam": NislamParams,
    "fastorb": FastOrbParams,
    "mavlink": MavlinkConfig,
    "zenoh": ZenohConfig,
    "ahrs": AhrsConfig,
    "myahrs": MyAhrsConfig,
    "autopilot": AutopilotConfig,
    "oak": OakConfig,
    "record": RecordConfig,
    "service": ServiceConfig,
}


# --------------------------------------------------------------------------- rules


@dataclass(frozen=True)
class Range:
    """A numeric interval; `None` bounds are open-ended."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False

    def violation(self, value: Any) -> str | None:
        lo_ok = self.lo is None or (value > self.lo if self.lo_open else value >= self.lo)
        hi_ok = self.hi is None or (value < self.hi if self.hi_open else value <= self.hi)
        if lo_ok and hi_ok:
            return None
        if self.hi is None:
            return f"must be {'>' if self.lo_open else '>='} {self.lo:g}"
        if self.lo is None:
            return f"must be {'<' if self.hi_open else '<='} {self.hi:g}"
        left, right = "(" if self.lo_open else "[", ")" if self.hi_open else "]"
        return f"must be in {left}{self.lo:g}, {self.hi:g}{right}"


@dataclass(frozen=True)
class Choice:
    options: tuple[str, ...]

    def violation(self, value: Any) -> str | None:
        if value in self.options:
            return None
        return f"must be one of {', '.join(repr(o) for o in self.options)}"


@dataclass(frozen=True)
class Check:
    """Any other rule: `problem(value)` returns what is wrong, or None."""

    problem: Callable[[Any], str | None]

    def violation(self, value: Any) -> str | None:
        return self.problem(value)


_MAVLINK_HOST_PORT = re.compile(r"^(udp|udpin|udpout|udpbcast|tcp|tcpin|mcast):[^:]*:\d{1,5}$")
_ZENOH_ENDPOINT = re.compile(r"^[a-z0-9]+/\S+$")
_KEY_CHUNK = re.compile(r"^[A-Za-z0-9_.-]+$")


def _mavlink_connect_problem(value: str) -> str | None:
    """pymavlink connection strings: `udpout:HOST:PORT`, `tcp:HOST:PORT`, ...,
    or a serial device with an optional `,BAUD`."""
    if not value.strip():
        return "must not be empty"
    scheme = value.split(":", 1)[0]
    if ":" in value and scheme in ("udp", "udpin", "udpout", "udpbcast", "tcp", "tcpin", "mcast"):
        if not _MAVLINK_HOST_PORT.match(value):
            return f"must look like '{scheme}:HOST:PORT'"
    return None


def _zenoh_endpoints_problem(value: tuple[str, ...]) -> str | None:
    bad = [v for v in value if not _ZENOH_ENDPOINT.match(v)]
    return f"holds {bad[0]!r}: endpoints look like 'tcp/HOST:PORT'" if bad else None


def _key_chunk_problem(value: str) -> str | None:
    if _KEY_CHUNK.match(value):
        return None
    return "must be one zenoh key chunk: letters, digits, '_', '-', '.'"


def _unit_quaternion_problem(value: tuple[float, ...]) -> str | None:
    norm = math.sqrt(sum(v * v for v in value))
    return None if abs(norm - 1.0) < 1e-3 else f"must be a unit quaternion (norm {norm:.4g})"


POSITIVE = Range(lo=0.0, lo_open=True)
NON_NEGATIVE = Range(lo=0.0)
SHARE = Range(lo=0.0, hi=1.0, lo_open=True)  # (0, 1]
FRACTION = Range(lo=0.0, hi=1.0)  # [0, 1]
ANY = Range()

# Range rules by qualified key. Keys not listed fall back to DEFAULT_RULES by
# type (ints >= 0; floats only need to be finite, which the type check does).
RULES: dict[str, Range | Choice | Check] = {
    "replay.assoc_max_dt_s": POSITIVE,
    "replay.gt_max_gap_s": NON_NEGATIVE,
    "attitude.noise_deg": NON_NEGATIVE,
    "attitude.bias_deg_per_sqrt_s": NON_NEGATIVE,
    "attitude.offset_ms": ANY,
    "attitude.seed": NON_NEGATIVE,  # numpy's default_rng rejects negative seeds
    "tracker.name": Choice(TRACKER_NAMES),
    # sizes and counts
    "nislam.grid_width": POSITIVE,
    "nislam.grid_height": POSITIVE,
    "nislam.len_hist": POSITIVE,
    "nislam.hist_sample": POSITIVE,
    "nislam.pixel_stride": POSITIVE,
    "nislam.min_matched_cells": POSITIVE,
    "nislam.psr_exclude_cells": NON_NEGATIVE,
    # shares and fractions
    "nislam.adaptive_mu": SHARE,
    "nislam.min_valid_fraction": FRACTION,
    "nislam.time_offset_forget": SHARE,
    "nislam.layer_min_cover": SHARE,
    # lengths and scales
    "nislam.max_distance_m": POSITIVE,
    "nislam.min_depth_m": NON_NEGATIVE,
    "nislam.max_depth_m": POSITIVE,
    "nislam.kernel_sigma": POSITIVE,
    "nislam.lam": POSITIVE,  # ridge term of Eq. 12: 0 divides by the kernel spectrum alone
    "nislam.label_sigma_cells": NON_NEGATIVE,  # 0 = the paper's delta label
    "nislam.rate_half_window_s": POSITIVE,
    "nislam.search_radius_m": NON_NEGATIVE,
    "nislam.search_speed_m_s": NON_NEGATIVE,
    "nislam.max_coast_s": NON_NEGATIVE,
    "nislam.reuse_max_angle_deg": Range(lo=0.0, hi=90.0),  # optical axes apart by 90 deg share no view
    "nislam.reuse_max_dist_m": NON_NEGATIVE,
    "nislam.reuse_reset_jump_m": NON_NEGATIVE,
    # thresholds
    "nislam.psr_keyframe": NON_NEGATIVE,
    "nislam.psr_refine": NON_NEGATIVE,
    "nislam.psr_lost": NON_NEGATIVE,
    "nislam.gate_gray": POSITIVE,
    "nislam.gate_depth_m": POSITIVE,
    "nislam.depth_tilt_max_rad": NON_NEGATIVE,
    "nislam.time_offset_s": ANY,
    "nislam.time_offset_max_s": NON_NEGATIVE,
    # FastORB (onboard/fastorb.py); other ints >= 0, other floats finite
    "fastorb.clahe_clip_limit": POSITIVE,
    "fastorb.clahe_tiles": POSITIVE,
    "fastorb.orb_features": POSITIVE,
    "fastorb.orb_scale_factor": Range(lo=1.0, lo_open=True),
    "fastorb.orb_levels": POSITIVE,
    "fastorb.uam_accel_gain": FRACTION,
    "fastorb.lk_win_px": Range(lo=3),
    "fastorb.lk_max_iter": POSITIVE,
    "fastorb.lk_eps_px": POSITIVE,
    "fastorb.lk_max_error": POSITIVE,
    "fastorb.lk_min_eigen": NON_NEGATIVE,
    "fastorb.gms_grid_cols": POSITIVE,
    "fastorb.gms_grid_rows": POSITIVE,
    "fastorb.gms_alpha": NON_NEGATIVE,
    "fastorb.epipolar_threshold_px": POSITIVE,
    "fastorb.epipolar_confidence": Range(0.0, 1.0, lo_open=True, hi_open=True),
    "fastorb.pnp_reprojection_px": POSITIVE,
    "fastorb.pnp_iterations": POSITIVE,
    "fastorb.pnp_confidence": Range(0.0, 1.0, lo_open=True, hi_open=True),
    "fastorb.pnp_huber_px": NON_NEGATIVE,
    "fastorb.pnp_sigma_gate": NON_NEGATIVE,
    "fastorb.pnp_min_gate_px": POSITIVE,
    "fastorb.rgbd_bf_px": NON_NEGATIVE,
    "fastorb.rgbd_max_depth_m": POSITIVE,
    "fastorb.landmark_max_sd_m": POSITIVE,
    "fastorb.max_jump_m": POSITIVE,
    "fastorb.max_jump_deg": POSITIVE,
    "fastorb.min_depth_m": NON_NEGATIVE,
    "fastorb.max_depth_m": POSITIVE,
    "fastorb.depth_edge_rel": POSITIVE,
    "fastorb.min_point_distance_px": POSITIVE,
    "fastorb.map_track_every": POSITIVE,
    "fastorb.map_track_radius_px": POSITIVE,
    "fastorb.min_inliers": Range(lo=6),  # PnP needs at least 6 points
    "fastorb.keyframe_max_frames": POSITIVE,
    "fastorb.keyframe_inlier_ratio": FRACTION,
    "fastorb.local_map_keyframes": POSITIVE,
    "fastorb.max_keyframes": POSITIVE,
    "fastorb.match_radius_px": POSITIVE,
    "fastorb.match_max_hamming": Range(0, 256),
    "fastorb.reloc_ratio": SHARE,
    "fastorb.reloc_min_inliers": Range(lo=6),
    # outputs: MAVLink
    "mavlink.connect": Check(_mavlink_connect_problem),
    "mavlink.baud": POSITIVE,
    "mavlink.system_id": Range(1, 255),
    "mavlink.component_id": Range(1, 255),
    "mavlink.message": Choice(MAVLINK_MESSAGES),
    "mavlink.mount": Choice(MOUNT_NAMES),
    "mavlink.mount_q_B_C_xyzw": Check(_unit_quaternion_problem),
    "mavlink.world_frame": Choice(WORLD_FRAMES),
    "mavlink.degraded_quality": Range(0, 100),
    "mavlink.jump_m": NON_NEGATIVE,
    "mavlink.jump_speed_m_s": POSITIVE,
    "mavlink.velocity_window_s": NON_NEGATIVE,
    "mavlink.heartbeat_period_s": POSITIVE,
    "mavlink.stale_s": POSITIVE,
    "mavlink.reconnect_s": POSITIVE,
    "mavlink.queue_frames": POSITIVE,
    "mavlink.origin_lat_deg": Range(-90.0, 90.0),
    "mavlink.origin_lon_deg": Range(-180.0, 180.0),
    "mavlink.origin_alt_m": ANY,
    # outputs: zenoh
    "zenoh.vehicle": Check(_key_chunk_problem),
    "zenoh.mode": Choice(ZENOH_MODES),
    "zenoh.connect": Check(_zenoh_endpoints_problem),
    "zenoh.listen": Check(_zenoh_endpoints_problem),
    "zenoh.status_period_s": POSITIVE,
    "zenoh.queue_frames": POSITIVE,
    "zenoh.map_max_mb": POSITIVE,
    # drivers and recording
    "ahrs.source": Choice(AHRS_SOURCES),
    "ahrs.buffer_samples": Range(lo=2),
    "ahrs.max_age_s": POSITIVE,
    "ahrs.max_gap_s": POSITIVE,
    "myahrs.port": Check(lambda v: None if v.strip() else "must not be empty"),
    "myahrs.baud": POSITIVE,
    "myahrs.divider": Range(1, 100),
    "myahrs.latency_ms": ANY,
    "myahrs.q_B_A_xyzw": Check(_unit_quaternion_problem),
    "myahrs.silence_s": POSITIVE,
    "myahrs.reopen_s": POSITIVE,
    "myahrs.reconnect_max_s": POSITIVE,
    "autopilot.rate_hz": Range(0.0, 1000.0, lo_open=True),
    "autopilot.target_component": Range(0, 255),
    "autopilot.latency_ms": ANY,
    "autopilot.q_B_A_xyzw": Check(_unit_quaternion_problem),
    "autopilot.retry_s": POSITIVE,
    "autopilot.clock_window_s": POSITIVE,
    "oak.width": POSITIVE,
    "oak.height": POSITIVE,
    "oak.fps": POSITIVE,
    "oak.mono_width": POSITIVE,
    "oak.mono_height": POSITIVE,
    "oak.stereo_preset": Choice(OAK_STEREO_PRESETS),
    "oak.imu_rate_hz": Range(1, 400),
    "oak.imu_world": Choice(OAK_IMU_WORLDS),
    "oak.imu_q_B_A_xyzw": Check(_unit_quaternion_problem),
    "oak.search_s": POSITIVE,
    "oak.frame_timeout_s": POSITIVE,
    "oak.reconnect_max_s": POSITIVE,
    "record.png_compression": Range(0, 9),
    "record.queue_frames": POSITIVE,
    "record.start_timeout_s": POSITIVE,
    "service.fallback_tracker": Choice(("",) + tuple(n for n in TRACKER_NAMES if n != "nislam")),
    "service.return_after_s": NON_NEGATIVE,
    "service.frame_timeout_s": POSITIVE,
    "service.degraded_gap_s": POSITIVE,
    "service.start_grace_s": POSITIVE,
    "service.recover_s": NON_NEGATIVE,
    "service.poll_s": Range(0.001, 1.0),
    "service.attitude_wait_s": Range(0.0, 1.0),
    "service.stats_period_s": POSITIVE,
    "service.replay_speed": Range(0.01, 100.0),
}
DEFAULT_RULES: dict[type, Range] = {int: NON_NEGATIVE, float: ANY}

# Pairs that must satisfy first < second; checked only when both fields exist.
ORDERED: tuple[tuple[str, str], ...] = (
    ("nislam.min_depth_m", "nislam.max_depth_m"),
    ("fastorb.min_depth_m", "fastorb.max_depth_m"),
)


# --------------------------------------------------------------------------- loading


def load_config(
    path: Path | str | None = None,
    overrides: Mapping[str, Any] | None = None,
    overrides_origin: str = "overrides",
) -> Config:
    """Defaults, then the TOML file at `path`, then `overrides`.

    `overrides` maps qualified keys to values, e.g. {"attitude.noise_deg": 1.0};
    `overrides_origin` names them in error messages (e.g. "command line").
    Raises NislamError naming the offending key.
    """
    values: dict[str, dict[str, Any]] = {name: {} for name in SECTIONS}
    if path is not None:
        origin = str(path)
        for key, value in _flatten(_read_toml(Path(path)), origin).items():
            _set(values, key, value, origin)
    for key, value in (overrides or {}).items():
        _set(values, key, value, overrides_origin)
    cfg = Config(**{name: SECTIONS[name](**values[name]) for name in SECTIONS})
    _check_order(cfg, str(path) if path is not None else "config")
    log.debug("effective config:\n%s", config_to_toml(cfg))
    return cfg


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise NislamError(f"{path}: config file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise NislamError(f"{path}: cannot read config: {e}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise NislamError(f"{path}: not valid TOML: {e}") from None


def _flatten(raw: dict[str, Any], origin: str) -> dict[str, Any]:
    """{section: {key: value}} -> {"section.key": value}."""
    flat: dict[str, Any] = {}
    for section, table in raw.items():
        if section not in SECTIONS:
            raise NislamError(
                f"{origin}: unknown section '{section}' (known: {', '.join(SECTIONS)})"
            )
        if not isinstance(table, dict):
            raise NislamError(f"{origin}: '{section}' must be a table ([{section}])")
        for key, value in table.items():
            flat[f"{section}.{key}"] = value
    return flat


def _set(values: dict[str, dict[str, Any]], key: str, value: Any, origin: str) -> None:
    section, _, name = key.partition(".")
    types = _field_types(SECTIONS[section]) if section in SECTIONS else {}
    if name not in types:
        raise NislamError(f"{origin}: unknown key '{key}'")
    checked = _check_type(key, value, types[name], origin)
    rule = RULES.get(key) or DEFAULT_RULES.get(type(checked))
    problem = rule.violation(checked) if rule is not None else None
    if problem is not None:
        raise NislamError(f"{origin}: '{key}' {problem}, got {checked!r}")
    values[section][name] = checked


def _field_types(cls: type) -> dict[str, Any]:
    # get_type_hints resolves the string annotations of `from __future__ import annotations`.
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


_TYPE_WORDS = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}


def _check_type(key: str, value: Any, tp: Any, origin: str) -> Any:
    """The value converted to the field's type (int -> float), or NislamError."""
    if tp in _TYPE_WORDS:
        ok = _scalar(value, tp)
        if ok is None:
            raise NislamError(
                f"{origin}: '{key}' must be {_TYPE_WORDS[tp]}, got {_toml_type(value)}"
            )
        return ok
    if typing.get_origin(tp) is tuple:
        args = typing.get_args(tp)
        item = args[0] if args else Any
        items = [_scalar(v, item) for v in value] if isinstance(value, list) else None
        if items is None or any(v is None for v in items):
            raise NislamError(
                f"{origin}: '{key}' must be an array of {getattr(item, '__name__', item)} values"
            )
        if len(args) >= 2 and args[1] is not Ellipsis and len(items) != len(args):
            raise NislamError(f"{origin}: '{key}' must hold {len(args)} values, got {len(items)}")
        return tuple(items)
    raise NislamError(f"{origin}: '{key}' has type {tp} that a config file cannot set")


def _scalar(value: Any, tp: Any) -> Any:
    """`value` as `tp`, or None. bool is an int subclass in Python, but
    `grid_width = true` is a typo, not 1; an int is a fine float."""
    if tp is bool:
        return value if isinstance(value, bool) else None
    if isinstance(value, bool):
        return None
    if tp is int:
        return value if isinstance(value, int) else None
    if tp is float:
        if isinstance(value, (int, float)) and math.isfinite(value):
            return float(value)
        return None
    if tp is str:
        return value if isinstance(value, str) else None
    return None


def _toml_type(value: Any) -> str:
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)
    return type(value).__name__


def _check_order(cfg: Config, origin: str) -> None:
    for lo_key, hi_key in ORDERED:
        lo, hi = _get(cfg, lo_key), _get(cfg, hi_key)
        if lo is not None and hi is not None and not lo < hi:
            raise NislamError(f"{origin}: '{lo_key}' ({lo:g}) must be < '{hi_key}' ({hi:g})")


def _get(cfg: Config, key: str) -> Any:
    section, _, name = key.partition(".")
    return getattr(getattr(cfg, section), name, None)


# --------------------------------------------------------------------------- writing


def config_to_dict(cfg: Config) -> dict[str, dict[str, Any]]:
    """Every value of every section, TOML-ready (tuples as lists)."""
    out: dict[str, dict[str, Any]] = {}
    for section in SECTIONS:
        obj = getattr(cfg, section)
        out[section] = {
            f.name: _to_toml(getattr(obj, f.name)) for f in dataclasses.fields(obj)
        }
    return out


def config_to_toml(cfg: Config) -> str:
    """The effective config as TOML; `load_config` of it gives `cfg` back."""
    header = f"# Effective configuration (nislam-onboard {__version__}): every value used.\n\n"
    return header + tomli_w.dumps(config_to_dict(cfg))


def _to_toml(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value
