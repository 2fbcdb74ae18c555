"""Where `nislam run` gets its frames and attitude: the configured hardware
(drivers) or a recording replayed at its own pace through the same interfaces.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from onboard.app.config import Config
from onboard.core.attitude import AttitudeBuffer
from onboard.core.sources import CameraSource


@dataclass
class Sources:
    """What the loop reads: a camera, the attitude buffer, and the object that
    starts and stops their threads (onboard.app.hardware.Hardware or
    sim_replay.sources.Replay). `sequence`: the replayed recording (ground
    truth for the final score), None on hardware."""

    label: str
    camera: CameraSource
    attitude: AttitudeBuffer
    runner: Any  # .start(), .stop(timeout_s) -> bool, .stop_times_s
    link: Any = None  # drivers.fc_link.FcLink shared with the MAVLink output
    sequence: Any = None  # sim_replay.tum.Sequence
    attitude_label: str = ""
    looped: bool = False  # a replay played back and forth: its poses map to no ground truth
    # Frame stamps -> host monotonic time [s] when the stamps are not on that
    # clock (a replay keeps the recording's); None: they are.
    host_time_s: Callable[[float], float] | None = None
    host_mapping: Callable[[], dict[str, float] | None] | None = None  # for metrics.json
    source_stats: Callable[[], dict[str, Any]] | None = None  # the source's own, for metrics.json
    # Each driver's state (drivers.device_state.DeviceSnapshot), for the health
    # line, the zenoh status and systemd; None for replays.
    devices: Callable[[], list[Any]] | None = None

    def start(self) -> None:
        self.runner.start()

    def stop(self) -> dict[str, float]:
        self.runner.stop()
        return dict(self.runner.stop_times_s)


def hardware_sources(cfg: Config, **make_kwargs: Any) -> Sources:
    """The OAK-D and the configured AHRS (onboard.app.hardware.make_hardware;
    `make_kwargs` go to it, e.g. a stand-in depthai for tests)."""
    from onboard.app.hardware import make_hardware

    hw = make_hardware(cfg, camera=True, **make_kwargs)
    assert hw.camera is not None
    return Sources("OAK-D", hw.camera, hw.buffer, hw, link=hw.link,
                   attitude_label=hw.attitude_label, devices=hw.device_states)


def replay_sources(cfg: Config, seq_dir: Path | str, loop_s: float | None = None
                   ) -> tuple[Sources, Config]:
    """A recording replayed at `[service] replay_speed` through the driver
    interfaces; with `loop_s`, forwards and backwards in turn for at least
    that long (then there is no ground truth to score against). The camera
    mount comes from the recording (one source of truth for R_B_C): the
    config's [mavlink] mount is set to it."""
    from onboard.core.rotations import matrix_to_quat
    from sim_replay.sources import open_replay

    rp = open_replay(seq_dir, speed=cfg.service.replay_speed,
                     buffer_capacity=cfg.ahrs.buffer_samples, max_gap_s=cfg.ahrs.max_gap_s,
                     assoc_max_dt_s=cfg.replay.assoc_max_dt_s, undistort=cfg.replay.undistort,
                     stamp_window_s=cfg.replay.stamp_window_s,
                     loop_s=loop_s, attitude_smoothing_s=cfg.ahrs.smoothing_s,
                     attitude_smoothing_max_s=cfg.ahrs.smoothing_max_s,
                     ahrs_noise_deg=cfg.nislam.attitude_sd_deg)
    passes = rp.passes
    q = matrix_to_quat(rp.buffer.R_B_C)
    mav = dataclasses.replace(cfg.mavlink, mount="custom", mount_q_B_C_xyzw=tuple(q))
    cfg = dataclasses.replace(cfg, mavlink=mav)
    label = f"replay of {rp.seq.path}" + (f" ({passes} passes)" if passes > 1 else "")
    return Sources(label, rp.camera, rp.buffer, rp, sequence=rp.seq if passes == 1 else None,
                   attitude_label=rp.attitude_label, looped=passes > 1,
                   host_time_s=rp.clock.host_time_s, host_mapping=rp.clock.host_mapping), cfg


@dataclass
class ThreadGroup:
    """Driver threads started in order and stopped in reverse (as
    onboard.app.hardware.Hardware); `stop_times_s` records each join."""

    threads: list[Any]
    stop_times_s: dict[str, float] = dataclasses.field(default_factory=dict)

    def start(self) -> None:
        for t in self.threads:
            t.start()

    def stop(self, timeout_s: float = 5.0) -> bool:
        ok = True
        for t in reversed(self.threads):
            ok = t.stop(timeout_s) and ok
            self.stop_times_s[t.name] = t.last_stop_s or 0.0
        return ok


SIM_FOLLOW_ANCHOR_FILE = "sim_follow_anchor.json"


def cache_directory(env: dict[str, str] | None = None) -> Path:
    """Rebuildable files (the synthetic scenes' textures): systemd's
    $CACHE_DIRECTORY, else $XDG_CACHE_HOME/nislam, else ~/.cache/nislam."""
    env = dict(os.environ) if env is None else env
    if env.get("CACHE_DIRECTORY"):
        return Path(env["CACHE_DIRECTORY"].split(":")[0])
    base = env.get("XDG_CACHE_HOME") or str(Path(env.get("HOME", "~")).expanduser() / ".cache")
    return Path(base) / "nislam"


def follow_sources(cfg: Config, name: str) -> Sources:
    """`--sim-follow NAME`: the vehicle's true state from the simulator on the
    [mavlink] link (SIM_STATE or HIL_STATE_QUATERNION, requested with
    SET_MESSAGE_INTERVAL), the camera and AHRS rendered from it in real time
    (sim_replay.follow). The MAVLink feed shares the link, so the simulated
    autopilot flies on our poses; the camera's truth is scored at the end.
    Without [mavlink] set_origin the vehicle's start becomes the EKF origin."""
    from drivers.message_interval import MessageInterval
    from onboard.app.hardware import camera_mount_q, make_attitude_buffer, make_fc_link
    from onboard.core.rotations import mount_rotation
    from onboard.outputs.mavlink_origin import state_directory
    from sim_replay.follow import open_follow
    from sim_replay.follow_state import STATE_TYPES

    sf, m = cfg.sim_follow, cfg.mavlink
    # The simulated AHRS sends samples missed in a stall late, by design
    # (sim_replay.follow CATCH_UP_S): no time-jump check on its stamps.
    buffer = make_attitude_buffer(cfg, check_stamps=False)
    fol = open_follow(
        name, R_B_C=mount_rotation(m.mount, m.mount_q_B_C_xyzw), q_B_C_xyzw=camera_mount_q(cfg),
        sink=buffer.push, width=sf.width, height=sf.height, camera_hz=sf.camera_hz,
        ahrs_profile_name=sf.ahrs_profile, ahrs_hz=sf.ahrs_hz, start_height_m=sf.start_height_m,
        position_tau_s=sf.position_tau_s, seed=sf.seed,
        anchor_file=state_directory(m.state_dir) / SIM_FOLLOW_ANCHOR_FILE,
        texture_cache=cache_directory(), render_process=sf.render_process)
    link = make_fc_link(cfg)
    link.add_listener(fol.track.push_message, STATE_TYPES)
    threads: list[Any] = [link]
    if sf.request != "none":
        threads.append(MessageInterval(link, sf.request, sf.state_rate_hz,
                                       target_system=m.system_id,
                                       target_component=sf.target_component))
    if not m.set_origin:  # the EKF needs one: the vehicle's start (onboard.app.sim_origin)
        from onboard.app.sim_origin import OriginFromVehicle

        threads.append(OriginFromVehicle(link, fol.track, m))
    threads += [fol.ahrs, fol.camera]
    return Sources(fol.label, fol.camera, buffer, ThreadGroup(threads), link=link,
                   sequence=fol.truth, attitude_label=f"simulated AHRS ({sf.ahrs_profile})",
                   source_stats=fol.stats, devices=lambda: [link.device_state.snapshot()])
