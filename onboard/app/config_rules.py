"""What a configuration value may be: ranges, choices and checks by qualified
key, each violation one line naming the key.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from drivers.oak import IMU_WORLDS, STEREO_PRESETS
from onboard.app.config_sections import AHRS_SOURCES, SIM_FOLLOW_REQUESTS
from onboard.fusion.registry import AUTO, TRACKER_NAMES
from onboard.outputs.settings import (
    MAVLINK_MESSAGES,
    MOUNT_NAMES,
    WORLD_FRAMES,
    ZENOH_MODES,
    ZENOH_PRIORITIES,
)


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


_ZENOH_ENDPOINT = re.compile(r"^[a-z0-9]+/\S+$")


_KEY_CHUNK = re.compile(r"^[A-Za-z0-9_.-]+$")


_MAVLINK_SCHEMES = ("udp", "udpin", "udpout", "udpbcast", "tcp", "tcpin", "mcast")
_HOST = re.compile(r"^[A-Za-z0-9][A-Za-z0-9.-]*$")  # a name or an IPv4 address
_SERIAL = re.compile(r"^(/\S+|COM\d+)(,\d+)?$")  # /dev/ttyACM0, /dev/serial/by-id/..,57600


def _mavlink_connect_problem(value: str) -> str | None:
    """pymavlink connection strings: `udpout:HOST:PORT`, `tcp:HOST:PORT`, ...
    (port 1-65535), or a serial device path with an optional `,BAUD`."""
    v = value.strip()
    if not v:
        return "must not be empty"
    if _SERIAL.match(v):
        return None
    scheme, sep, rest = v.partition(":")
    if not sep or scheme not in _MAVLINK_SCHEMES:
        return (f"must be SCHEME:HOST:PORT (SCHEME one of {', '.join(_MAVLINK_SCHEMES)}) "
                f"or a serial device (/dev/...[,BAUD]), got {v!r}")
    if scheme == "mcast" and not rest:
        return None  # pymavlink's default group and port
    host, sep, port = rest.rpartition(":")
    if not sep or not _HOST.match(host):
        return f"must look like '{scheme}:HOST:PORT', got {v!r}"
    if not port.isdigit() or not 1 <= int(port) <= 65535:
        return f"port must be in 1..65535, got {port!r}"
    return None


def _zenoh_endpoints_problem(value: tuple[str, ...]) -> str | None:
    bad = [v for v in value if not _ZENOH_ENDPOINT.match(v)]
    return f"holds {bad[0]!r}: endpoints look like 'tcp/HOST:PORT'" if bad else None


def _key_chunk_problem(value: str) -> str | None:
    if _KEY_CHUNK.match(value):
        return None
    return "must be one zenoh key chunk: letters, digits, '_', '-', '.'"


def _key_chunks_problem(value: tuple[str, ...]) -> str | None:
    bad = [v for v in value if not _KEY_CHUNK.match(v)]
    return f"holds {bad[0]!r}: each must be one zenoh key chunk (a vehicle id)" if bad else None


def _common_names_problem(value: tuple[str, ...]) -> str | None:
    return "must not hold an empty name" if any(not v.strip() for v in value) else None


def _unit_quaternion_problem(value: tuple[float, ...]) -> str | None:
    norm = math.sqrt(sum(v * v for v in value))
    return None if abs(norm - 1.0) < 1e-3 else f"must be a unit quaternion (norm {norm:.4g})"


def _ahrs_profile_problem(value: str) -> str | None:
    from sim_replay.sensors import AHRS_PROFILES  # numpy/OpenCV: only when the key is checked

    return None if value in AHRS_PROFILES else (
        f"must be one of {', '.join(repr(p) for p in AHRS_PROFILES)}")


def _dir_problem(value: str) -> str | None:
    """A directory path or "" (the default place); created when missing."""
    return "must not hold a NUL character" if "\0" in value else None


POSITIVE = Range(lo=0.0, lo_open=True)


NON_NEGATIVE = Range(lo=0.0)


SHARE = Range(lo=0.0, hi=1.0, lo_open=True)  # (0, 1]


FRACTION = Range(lo=0.0, hi=1.0)  # [0, 1]


ANY = Range()


# Upper bounds on sizes, rates, durations and queue lengths: a typo (an extra
# zero) is one line at start-up, not an out-of-memory kill or a service that
# waits an hour before it notices a dead sensor.
DURATION = Range(0.0, 3600.0, lo_open=True)  # (0 s, 1 h]
DURATION0 = Range(0.0, 3600.0)  # [0 s, 1 h]
QUEUE = Range(1, 10_000)  # items held in memory
IMAGE_PX = Range(16, 4096)
BAUD = Range(1200, 12_000_000)


# Range rules by qualified key. Keys not listed fall back to DEFAULT_RULES by
# type (ints >= 0; floats only need to be finite, which the type check does).
RULES: dict[str, Range | Choice | Check] = {
    "replay.assoc_max_dt_s": POSITIVE,
    "replay.stamp_window_s": NON_NEGATIVE,
    "replay.gt_max_gap_s": NON_NEGATIVE,
    "attitude.noise_deg": NON_NEGATIVE,
    "attitude.bias_deg_per_sqrt_s": NON_NEGATIVE,
    "attitude.offset_ms": ANY,
    "attitude.seed": NON_NEGATIVE,  # numpy's default_rng rejects negative seeds
    "tracker.name": Choice((AUTO,) + TRACKER_NAMES),
    # sizes and counts
    "nislam.grid_width": POSITIVE,
    "nislam.grid_height": POSITIVE,
    "nislam.len_hist": POSITIVE,
    "nislam.hist_sample": POSITIVE,
    "nislam.pixel_stride": POSITIVE,
    "nislam.max_point_spacing_cells": NON_NEGATIVE,
    "nislam.key_depth_stride": NON_NEGATIVE,
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
    "nislam.attitude_sd_deg": NON_NEGATIVE,
    "nislam.search_radius_m": NON_NEGATIVE,
    "nislam.search_speed_m_s": NON_NEGATIVE,
    "nislam.max_coast_s": NON_NEGATIVE,
    "nislam.reuse_max_angle_deg": Range(lo=0.0, hi=90.0),  # optical axes apart by 90 deg share no view
    "nislam.reuse_max_dist_m": NON_NEGATIVE,
    "nislam.reuse_reset_jump_m": NON_NEGATIVE,
    "nislam.link_every_n_frames": NON_NEGATIVE,  # 0 = keys linked only at re-uses
    # thresholds
    "nislam.psr_keyframe": NON_NEGATIVE,
    "nislam.psr_refine": NON_NEGATIVE,
    "nislam.psr_lost": NON_NEGATIVE,
    "nislam.gate_gray": POSITIVE,
    "nislam.gate_depth_m": POSITIVE,
    "nislam.depth_tilt_max_rad": NON_NEGATIVE,
    "nislam.depth_gate_sigmas": NON_NEGATIVE,
    "nislam.depth_all_cells_sd_m": NON_NEGATIVE,
    "nislam.depth_front_mean_m": NON_NEGATIVE,
    "nislam.time_offset_s": ANY,
    "nislam.time_offset_max_s": NON_NEGATIVE,
    "nislam.rolling_shutter_readout_s": Range(lo=-1.0, hi=0.1),  # -1: the camera's
    "nislam.rolling_shutter_rate_half_window_s": POSITIVE,
    # FastORB (onboard/fastorb/); other ints >= 0, other floats finite
    "fusion.accel_sd_m_s2": POSITIVE,
    "fusion.initial_speed_sd_m_s": POSITIVE,
    "fusion.gate_chi2": POSITIVE,
    "fusion.outlier_chi2": POSITIVE,
    "fusion.outlier_prior_dof": NON_NEGATIVE,
    "fusion.key_clones": POSITIVE,
    "fusion.noise_adapt_gain": FRACTION,
    "fusion.noise_scale_max": Range(lo=1.0),
    "fusion.nislam_var_scale": POSITIVE,
    "fusion.fastorb_var_scale": POSITIVE,
    "fusion.psr_full": NON_NEGATIVE,
    "fusion.nislam_peak_cells": POSITIVE,
    "fusion.nislam_cells_per_sample": Range(lo=1.0),
    "fusion.min_sd_m": POSITIVE,
    "fusion.max_coast_s": NON_NEGATIVE,
    "fusion.axes_gain": FRACTION,
    "fusion.velocity_clones": NON_NEGATIVE,
    "fusion.quality_sd_m": POSITIVE,
    "fastorb.clahe_clip_limit": POSITIVE,
    "fastorb.rolling_shutter_readout_s": Range(lo=-1.0, hi=0.1),  # -1: the camera's
    "fastorb.rolling_shutter_rate_sd": POSITIVE,
    "fastorb.local_ba_depth_sd": POSITIVE,
    "fastorb.local_ba_pixel_sd": POSITIVE,
    "fastorb.local_ba_max_points": POSITIVE,
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
    "fastorb.map_match_lk_px": NON_NEGATIVE,
    "fastorb.reloc_ratio": SHARE,
    "fastorb.reloc_min_inliers": Range(lo=6),
    # outputs: MAVLink
    "mavlink.connect": Check(_mavlink_connect_problem),
    "mavlink.baud": BAUD,
    "mavlink.system_id": Range(1, 255),
    "mavlink.component_id": Range(1, 255),
    "mavlink.message": Choice(MAVLINK_MESSAGES),
    "mavlink.mount": Choice(MOUNT_NAMES),
    "mavlink.mount_q_B_C_xyzw": Check(_unit_quaternion_problem),
    "mavlink.world_frame": Choice(WORLD_FRAMES),
    "mavlink.degraded_quality": Range(0, 100),
    "mavlink.jump_m": NON_NEGATIVE,
    "mavlink.jump_speed_m_s": POSITIVE,
    "mavlink.velocity_window_s": Range(0.0, 10.0),
    "mavlink.heartbeat_period_s": Range(0.0, 60.0, lo_open=True),
    "mavlink.stale_s": DURATION,
    "mavlink.reconnect_s": DURATION,
    "mavlink.queue_frames": QUEUE,
    "mavlink.origin_lat_deg": Range(-90.0, 90.0),
    "mavlink.origin_lon_deg": Range(-180.0, 180.0),
    "mavlink.origin_alt_m": ANY,
    "mavlink.state_dir": Check(_dir_problem),
    # outputs: zenoh
    "zenoh.vehicle": Check(_key_chunk_problem),
    "zenoh.mode": Choice(ZENOH_MODES),
    "zenoh.connect": Check(_zenoh_endpoints_problem),
    "zenoh.listen": Check(_zenoh_endpoints_problem),
    "zenoh.status_period_s": DURATION,
    "zenoh.queue_frames": QUEUE,
    "zenoh.map_max_mb": Range(0.0, 65536.0, lo_open=True),
    "zenoh.map_rate_kb_s": NON_NEGATIVE,
    "zenoh.pose_priority": Choice(ZENOH_PRIORITIES),
    "zenoh.status_priority": Choice(ZENOH_PRIORITIES),
    "zenoh.map_priority": Choice(ZENOH_PRIORITIES),
    "router.listen": Check(_zenoh_endpoints_problem),
    "router.connect": Check(_zenoh_endpoints_problem),
    "router.vehicles": Check(_key_chunks_problem),
    "router.grounds": Check(_common_names_problem),
    "mavlink.signing_link_id": Range(0, 255),
    # drivers and recording
    "ahrs.source": Choice(AHRS_SOURCES),
    "ahrs.buffer_samples": Range(2, 1_000_000),
    "ahrs.max_age_s": DURATION,
    "ahrs.max_gap_s": DURATION,
    "ahrs.smoothing_s": Range(0.0, 0.1),  # wider: the fit would flatten the vehicle's own motion
    "ahrs.smoothing_max_s": Range(0.0, 0.2),  # the ICI rule stops where the motion bends; a cap on the work
    "myahrs.port": Check(lambda v: None if v.strip() else "must not be empty"),
    "myahrs.baud": BAUD,
    "myahrs.divider": Range(1, 100),
    "myahrs.latency_ms": ANY,
    "myahrs.q_B_A_xyzw": Check(_unit_quaternion_problem),
    "myahrs.silence_s": DURATION,
    "myahrs.reopen_s": DURATION,
    "myahrs.reconnect_max_s": DURATION,
    "autopilot.rate_hz": Range(0.0, 1000.0, lo_open=True),
    "autopilot.target_component": Range(0, 255),
    "autopilot.latency_ms": ANY,
    "autopilot.q_B_A_xyzw": Check(_unit_quaternion_problem),
    "autopilot.retry_s": DURATION,
    "autopilot.clock_window_s": DURATION,
    "oak.width": IMAGE_PX,
    "oak.height": IMAGE_PX,
    "oak.fps": Range(0.0, 120.0, lo_open=True),
    "oak.mono_width": IMAGE_PX,
    "oak.mono_height": IMAGE_PX,
    "oak.stereo_preset": Choice(STEREO_PRESETS),
    "oak.imu_rate_hz": Range(1, 400),
    "oak.imu_world": Choice(IMU_WORLDS),
    "oak.imu_q_B_A_xyzw": Check(_unit_quaternion_problem),
    "oak.search_s": Range(0.0, 60.0, lo_open=True),
    "oak.frame_timeout_s": DURATION,
    "oak.reconnect_max_s": DURATION,
    "record.png_compression": Range(0, 9),
    "record.queue_frames": QUEUE,
    "record.start_timeout_s": DURATION,
    "service.fallback_tracker": Choice(("",) + tuple(n for n in TRACKER_NAMES if n != "nislam")),
    "service.return_after_s": DURATION0,
    "service.frame_timeout_s": DURATION,
    "service.degraded_gap_s": DURATION,
    "service.start_grace_s": DURATION,
    "service.recover_s": DURATION0,
    "service.poll_s": Range(0.001, 1.0),
    "service.attitude_wait_s": Range(0.0, 1.0),
    "service.stats_period_s": DURATION,
    "service.replay_speed": Range(0.01, 100.0),
    "service.realtime_priority": Range(0, 49),  # below the kernel's IRQ threads (50)
    # nislam run --sim-follow
    "sim_follow.request": Choice(SIM_FOLLOW_REQUESTS),
    "sim_follow.state_rate_hz": Range(1.0, 1000.0),
    "sim_follow.target_component": Range(0, 255),
    "sim_follow.camera_hz": Range(1.0, 120.0),
    "sim_follow.width": Range(32, 4096),
    "sim_follow.height": Range(24, 4096),
    "sim_follow.ahrs_profile": Check(_ahrs_profile_problem),
    "sim_follow.ahrs_hz": Range(1.0, 1000.0),
    "sim_follow.start_height_m": Range(0.0, 2.0),
    "sim_follow.position_tau_s": Range(0.0, 10.0),
}


DEFAULT_RULES: dict[type, Range] = {int: NON_NEGATIVE, float: ANY}


# Pairs that must satisfy first < second; checked only when both fields exist.
ORDERED: tuple[tuple[str, str], ...] = (
    ("nislam.min_depth_m", "nislam.max_depth_m"),
    ("fastorb.min_depth_m", "fastorb.max_depth_m"),
)
