"""Where `nislam run` gets its frames and attitude: the configured hardware
(drivers) or a recording replayed at its own pace through the same interfaces.
"""

from __future__ import annotations

import dataclasses
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
                   attitude_label=hw.attitude_label)


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
                     loop_s=loop_s)
    passes = rp.passes
    q = matrix_to_quat(rp.buffer.R_B_C)
    mav = dataclasses.replace(cfg.mavlink, mount="custom", mount_q_B_C_xyzw=tuple(q))
    cfg = dataclasses.replace(cfg, mavlink=mav)
    label = f"replay of {rp.seq.path}" + (f" ({passes} passes)" if passes > 1 else "")
    return Sources(label, rp.camera, rp.buffer, rp, sequence=rp.seq if passes == 1 else None,
                   attitude_label=rp.attitude_label, looped=passes > 1,
                   host_time_s=rp.clock.host_time_s, host_mapping=rp.clock.host_mapping), cfg
