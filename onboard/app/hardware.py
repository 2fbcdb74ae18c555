"""Build the hardware drivers from config: the attitude buffer, the AHRS driver
that fills it, the OAK-D camera and the flight-controller link.

Constructors of the drivers take plain values; this factory is the one place
that reads the config sections ([ahrs], [myahrs], [autopilot], [oak] and the
[mavlink] link settings and camera mount).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from drivers.autopilot_attitude import AutopilotAttitude
from drivers.fc_link import FcLink
from drivers.myahrs import MyAhrsDriver
from drivers.oak import OakDriver, OakSettings, import_depthai
from onboard.core.attitude import AttitudeBuffer
from onboard.core.rotations import Quat, matrix_to_quat, mount_rotation
from onboard.core.sources import DriverThread

if TYPE_CHECKING:
    from onboard.app.config import Config


def camera_mount_q(cfg: Config) -> Quat:
    """q_B_C_xyzw of the configured camera mount ([mavlink] mount)."""
    return matrix_to_quat(mount_rotation(cfg.mavlink.mount, cfg.mavlink.mount_q_B_C_xyzw))


def make_attitude_buffer(cfg: Config, check_stamps: bool = True) -> AttitudeBuffer:
    a = cfg.ahrs
    R_B_C = mount_rotation(cfg.mavlink.mount, cfg.mavlink.mount_q_B_C_xyzw)
    # Live stamps are on time.monotonic_ns: a sample seconds away from it is a
    # time jump, dropped and told (onboard/core/attitude.py).
    label = {"myahrs": "myAHRS+", "autopilot": "autopilot attitude",
             "oak_imu": "OAK IMU"}.get(a.source, "AHRS")
    return AttitudeBuffer(R_B_C, a.buffer_samples, a.max_gap_s,
                          now_ns=time.monotonic_ns if check_stamps else None, label=label,
                          smoothing_s=a.smoothing_s, smoothing_max_s=a.smoothing_max_s,
                          noise_sd_deg=cfg.nislam.attitude_sd_deg)


def oak_settings(cfg: Config, imu: bool) -> OakSettings:
    o = cfg.oak
    return OakSettings(
        device=o.device, width=o.width, height=o.height, fps=o.fps,
        mono_width=o.mono_width, mono_height=o.mono_height, undistort=o.undistort,
        stereo_preset=o.stereo_preset, q_B_C_xyzw=camera_mount_q(cfg), imu=imu,
        imu_rate_hz=o.imu_rate_hz, imu_world=o.imu_world, imu_q_B_A_xyzw=o.imu_q_B_A_xyzw,
        search_s=o.search_s, frame_timeout_s=o.frame_timeout_s,
        reconnect_max_s=o.reconnect_max_s,
    )


def make_fc_link(cfg: Config, **kwargs: Any) -> FcLink:
    m = cfg.mavlink
    return FcLink(m.connect, baud=m.baud, source_system=m.system_id,
                  source_component=m.component_id, reconnect_max_s=m.reconnect_s, **kwargs)


@dataclass
class Hardware:
    """The drivers of one vehicle, started and stopped in order."""

    buffer: AttitudeBuffer
    camera: OakDriver | None = None
    link: FcLink | None = None  # the one link to the autopilot, for the MAVLink output too
    ahrs: DriverThread | None = None
    attitude_label: str = "none"
    threads: list[DriverThread] = field(default_factory=list)  # start order
    stop_times_s: dict[str, float] = field(default_factory=dict)

    def start(self) -> None:
        for t in self.threads:
            t.start()

    def device_states(self) -> list[Any]:
        """Each driver's drivers.device_state.DeviceState snapshot, in start order."""
        snaps = [t.device_state.snapshot() for t in self.threads if hasattr(t, "device_state")]
        stamps = self.buffer.stamps.snapshot()  # the AHRS's stamps: shown while they are wrong
        return snaps + [stamps] if stamps.state.failed else snaps

    def stop(self, timeout_s: float = 5.0) -> bool:
        """Stop in reverse start order; `stop_times_s` records each join."""
        ok = True
        for t in reversed(self.threads):
            ok = t.stop(timeout_s) and ok
            self.stop_times_s[t.name] = t.last_stop_s or 0.0
        return ok


def make_hardware(cfg: Config, *, camera: bool = True,
                  dai_loader: Callable[[], Any] = import_depthai) -> Hardware:
    """The configured AHRS (cfg.ahrs.source) feeding a fresh buffer, plus the
    OAK-D when `camera` (or when the OAK IMU is the AHRS: one device)."""
    buffer = make_attitude_buffer(cfg)
    hw = Hardware(buffer, attitude_label=cfg.ahrs.source)
    source = cfg.ahrs.source
    if camera or source == "oak_imu":
        imu_sink = buffer.push if source == "oak_imu" else None
        hw.camera = OakDriver(oak_settings(cfg, imu=source == "oak_imu"), imu_sink=imu_sink,
                              dai_loader=dai_loader)
        hw.threads.append(hw.camera)
    if source == "myahrs":
        m = cfg.myahrs
        hw.ahrs = MyAhrsDriver(m.port, buffer.push, baud=m.baud, divider=m.divider,
                               latency_ms=m.latency_ms, q_B_A_xyzw=m.q_B_A_xyzw,
                               silence_s=m.silence_s, reopen_after_s=m.reopen_s,
                               reconnect_max_s=m.reconnect_max_s)
        hw.threads.append(hw.ahrs)
    elif source == "autopilot":
        a = cfg.autopilot
        hw.link = make_fc_link(cfg)
        hw.ahrs = AutopilotAttitude(
            hw.link, buffer.push, rate_hz=a.rate_hz, target_system=cfg.mavlink.system_id,
            target_component=a.target_component, latency_ms=a.latency_ms,
            q_B_A_xyzw=a.q_B_A_xyzw, retry_s=a.retry_s, clock_window_s=a.clock_window_s)
        hw.threads += [hw.link, hw.ahrs]
    elif source == "oak_imu":
        hw.ahrs = hw.camera
    return hw
