"""The application's configuration sections: replay, attitude error, tracker
choice, the drivers, recording and the service loop. The trackers' and the
outputs' sections live with them (NislamParams, FastOrbParams,
onboard.outputs.settings).
"""

from __future__ import annotations

from dataclasses import dataclass

from onboard.core.rotations import IDENTITY_Q_XYZW


@dataclass(frozen=True)
class ReplayConfig:
    """How a recorded sequence is read."""

    assoc_max_dt_s: float = 0.02  # rgb/depth pairing window (TUM associate.py default)
    gt_max_gap_s: float = 0.2  # ground truth / attitude interpolate across gaps up to this
    undistort: bool = True  # undistort colour and depth once with precomputed maps
    stamp_window_s: float = 1.0  # fit host-received stamps to the camera's clock over +- this [s]; 0 = as recorded


@dataclass(frozen=True)
class AttitudeErrorConfig:
    """Error added to the replayed attitude (see sim_replay.attitude.AttitudeErrorModel)."""

    noise_deg: float = 0.0
    bias_deg_per_sqrt_s: float = 0.0
    offset_ms: float = 0.0
    seed: int = 0


@dataclass(frozen=True)
class TrackerConfig:
    # "auto": `nislam run` runs "fused", `nislam replay` / `bench` "nislam"
    # (onboard.fusion.registry.resolve_name; app.config.with_tracker_resolved).
    name: str = "auto"


# Drivers (drivers/) and `nislam record`. The flight-controller link the
# autopilot attitude source uses is the [mavlink] one (connect, baud,
# system_id = the autopilot's system, reconnect_s): one link per autopilot.
# The camera mount R_B_C is [mavlink] mount / mount_q_B_C_xyzw.
AHRS_SOURCES = ("none", "myahrs", "autopilot", "oak_imu")


@dataclass(frozen=True)
class AhrsConfig:
    """Which AHRS feeds the attitude buffer (onboard/core/attitude.py), and the buffer."""

    source: str = "myahrs"  # "myahrs", "autopilot", "oak_imu" or "none"
    buffer_samples: int = 1024  # samples kept (10 s at 100 Hz)
    max_age_s: float = 0.25  # an AHRS this far behind a frame is not waited for (silent)
    max_gap_s: float = 0.1  # no interpolation across a longer gap between samples
    smoothing_s: float = 0.04  # attitude at a time: quadratic fit over +- this (core/attitude_smoothing.py)
    smoothing_max_s: float = 0.1  # ... widened up to +- this as far as the data allow, given the AHRS's noise


@dataclass(frozen=True)
class MyAhrsConfig:
    """myAHRS+ on a serial port (drivers/myahrs.py)."""

    port: str = "/dev/myahrs"  # a stable udev symlink, not /dev/ttyACMn
    baud: int = 115200
    divider: int = 1  # output rate 100 / divider Hz
    latency_ms: float = 0.0  # subtracted from each sample's arrival stamp
    q_B_A_xyzw: tuple[float, float, float, float] = IDENTITY_Q_XYZW  # AHRS axes -> body FRD
    silence_s: float = 1.0  # no sample this long: send the start-up commands again
    reopen_s: float = 3.0  # no sample this long: close and reopen the port
    reconnect_max_s: float = 2.0  # reopen backoff ceiling


@dataclass(frozen=True)
class AutopilotConfig:
    """ATTITUDE_QUATERNION from the autopilot over the [mavlink] link."""

    rate_hz: float = 50.0  # requested with MAV_CMD_SET_MESSAGE_INTERVAL
    target_component: int = 1  # the autopilot's component (0 = any)
    latency_ms: float = 0.0  # autopilot-internal delay, subtracted from mapped stamps
    q_B_A_xyzw: tuple[float, float, float, float] = IDENTITY_Q_XYZW  # autopilot body -> body
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
    imu_q_B_A_xyzw: tuple[float, float, float, float] = IDENTITY_Q_XYZW  # IMU axes -> body FRD
    search_s: float = 3.0  # device search per attempt
    frame_timeout_s: float = 2.0  # no frame this long = device lost, reconnect
    reconnect_max_s: float = 5.0  # reconnect backoff ceiling


@dataclass(frozen=True)
class RecordConfig:
    """`nislam record` (onboard/app/record.py)."""

    png_compression: int = 1  # 0-9: PNG zlib level (1 keeps up with 30 Hz on one core)
    queue_frames: int = 30  # frames waiting for the writer thread; when full the oldest is dropped
    start_timeout_s: float = 30.0  # give up when the camera is not up by then


@dataclass(frozen=True)
class ServiceConfig:
    """`nislam run`, the onboard loop (onboard/app/service.py)."""

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
    realtime_priority: int = 0  # SCHED_FIFO priority once the first frame is tracked (0: normal)


SIM_FOLLOW_REQUESTS = ("SIM_STATE", "HIL_STATE_QUATERNION", "none")


@dataclass(frozen=True)
class SimFollowConfig:
    """`nislam run --sim-follow SCENE`: the camera and AHRS rendered from a
    simulated vehicle's true state, read over the [mavlink] link
    (sim_replay/follow.py, docs/closed_loop.md)."""

    request: str = "SIM_STATE"  # asked for with MAV_CMD_SET_MESSAGE_INTERVAL ("none": sent anyway)
    state_rate_hz: float = 50.0  # ... at this rate
    target_component: int = 1  # the simulated autopilot's component
    camera_hz: float = 30.0
    width: int = 640  # rendered image size (focal length scales with the width)
    height: int = 480
    ahrs_profile: str = "perfect"  # simulated AHRS error: "perfect", "myahrs", "autopilot"
    ahrs_hz: float = 100.0
    start_height_m: float = 0.1  # the vehicle's first state is this high above the floor
    position_tau_s: float = 0.5  # smoothing of the reported position's lat/lon steps
    seed: int = 0  # textures and sensor noise
    render_process: bool = False  # render in a worker process of its own (off the tracker's GIL)
