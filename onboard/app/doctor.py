"""`nislam doctor`: the preflight check (ArduPilot's PreArm, PX4's preflight
checks). Probes, once and together, what the configuration names:

    camera   the OAK-D opens and streams at the configured size and rate
    ahrs     the AHRS gives valid samples at the expected rate
             (myAHRS+ on its port; the autopilot's attitude on the link;
             the OAK-D's IMU with the camera)
    mavlink  the autopilot's HEARTBEAT comes back on [mavlink] connect
    zenoh    each [zenoh] connect endpoint accepts a TCP connection
    disk     free space where recordings go
    clock    the wall clock is set (log names, TLS); stamps use CLOCK_MONOTONIC

and prints one row per check with a fix for each failure. Exit 1 when
anything the service needs fails (a warning does not count). The drivers
are the service's own (drivers/), so what doctor sees is what `nislam run`
will see.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from onboard.app.config import Config

log = logging.getLogger(__name__)

OK, FAIL, WARN, SKIP = "ok", "FAIL", "warn", "skip"
MIN_FREE_GB = 2.0  # a 10-minute recording at 640x400, 30 Hz
EPOCH_2024 = 1704067200.0  # a wall clock before this was never set (no RTC, no NTP yet)


@dataclass
class Check:
    name: str
    status: str
    detail: str
    fix: str = ""


def _state_detail(snap: Any) -> str:
    return f"{snap.where}: {snap.state.value}" + (f" ({snap.cause})" if snap.cause else "")


def _camera(cfg: Config, dai_loader: Callable[[], Any], wait_s: float, imu: bool) -> Callable:
    from drivers.oak import OakDriver
    from onboard.app.hardware import oak_settings

    samples: list[int] = []
    drv = OakDriver(oak_settings(cfg, imu=imu), dai_loader=dai_loader,
                    imu_sink=(lambda s: samples.append(1)) if imu else None)
    drv.start()

    def result() -> list[Check]:
        t0, f0 = time.monotonic(), drv.stats.frames
        drv.counters.wait_for(lambda s: s.frames >= f0 + 10, 1.0)
        hz = (drv.stats.frames - f0) / max(time.monotonic() - t0, 1e-3)
        snap = drv.device_state.snapshot()
        drv.stop(5.0)
        o = cfg.oak
        out = []
        if drv.stats.frames == 0:
            out.append(Check("camera (OAK-D)", FAIL, _state_detail(snap),
                             "plug the OAK-D in (USB 3 port; `lsusb | grep 03e7`), install "
                             "systemd/80-nislam-oakd.rules, set [oak] device if several"))
        elif hz < 0.8 * o.fps:
            out.append(Check("camera (OAK-D)", WARN, f"{o.width}x{o.height} at {hz:.1f} Hz, "
                             f"configured {o.fps:g} Hz", "a USB 2 port or cable? lower [oak] fps"))
        else:
            out.append(Check("camera (OAK-D)", OK, f"{o.width}x{o.height} at {hz:.1f} Hz"))
        if imu:
            out.append(Check("ahrs (OAK-D IMU)", OK if samples else FAIL,
                             f"{len(samples)} rotation-vector samples",
                             "" if samples else "a BNO08x OAK-D is needed for [ahrs] source = "
                             "\"oak_imu\"; or use myahrs / autopilot"))
        return out

    return result


def _myahrs(cfg: Config, wait_s: float) -> Callable:
    from drivers.myahrs import MyAhrsDriver

    m = cfg.myahrs
    n = [0]
    drv = MyAhrsDriver(m.port, lambda s: n.__setitem__(0, n[0] + 1), baud=m.baud,
                       divider=m.divider, silence_s=m.silence_s, reopen_after_s=m.reopen_s)
    drv.start()

    def result() -> list[Check]:
        t0, n0 = time.monotonic(), n[0]
        drv.counters.wait_for(lambda s: s.samples >= n0 + 20, 1.0)
        hz = (n[0] - n0) / max(time.monotonic() - t0, 1e-3)
        snap = drv.device_state.snapshot()
        drv.stop(5.0)
        want = 100.0 / m.divider
        if n[0] == 0:
            fix = {"no device": f"check [myahrs] port {m.port} (ls -l /dev/serial/by-id), "
                                f"permissions (the dialout group)",
                   "bad data": f"check [myahrs] baud ({m.baud}) and the wiring",
                   "silent": "power-cycle the myAHRS+; check TX/RX"}.get(snap.state.value,
                                                                     "check the myAHRS+")
            return [Check("ahrs (myAHRS+)", FAIL, _state_detail(snap), fix)]
        if hz < 0.8 * want:
            return [Check("ahrs (myAHRS+)", WARN, f"{m.port}: {hz:.0f} Hz, expected {want:.0f}",
                          "a lower [myahrs] divider, or a faster baud rate")]
        return [Check("ahrs (myAHRS+)", OK, f"{m.port}: valid samples at {hz:.0f} Hz")]

    return result


def _mavlink(cfg: Config, wait_s: float, need_attitude: bool) -> Callable:
    from onboard.app.hardware import make_fc_link

    link = make_fc_link(cfg)
    beats: list[Any] = []
    att: list[Any] = []
    link.add_listener(lambda msg, t: beats.append(msg), ("HEARTBEAT",))
    link.add_listener(lambda msg, t: att.append(msg), ("ATTITUDE_QUATERNION", "ATTITUDE"))
    link.start()
    deadline = time.monotonic() + wait_s

    def result() -> list[Check]:
        while not beats and time.monotonic() < deadline:
            # a heartbeat of ours: a udpout peer then knows where to answer
            link.send(lambda mav: mav.heartbeat_send(18, 8, 0, 0, 0))
            time.sleep(0.2)
        snap = link.device_state.snapshot()
        link.stop(5.0)
        c = cfg.mavlink.connect
        out = []
        if beats:
            b = beats[-1]
            out.append(Check("mavlink", OK, f"{c}: HEARTBEAT from system {b.get_srcSystem()} "
                             f"(autopilot type {b.autopilot})"))
        else:
            out.append(Check("mavlink", FAIL, f"{c}: no HEARTBEAT in {wait_s:.0f} s "
                             f"({snap.state.value}{': ' + snap.cause if snap.cause else ''})",
                             "check [mavlink] connect and the autopilot's telemetry port "
                             "(ArduPilot SERIALn_PROTOCOL = 2; PX4 MAV_n_CONFIG), baud rate"))
        if need_attitude:
            out.append(Check("ahrs (autopilot)", OK if att else FAIL,
                             f"{len(att)} attitude messages without asking",
                             "" if att else "the service asks for ATTITUDE_QUATERNION itself; "
                             "if `nislam run` reports no attitude, check SRn_EXTRA1"))
        return out

    return result


def _zenoh(cfg: Config) -> list[Check]:
    z = cfg.zenoh
    if not z.connect:
        return [Check("zenoh", OK, f"peer mode, listening on {', '.join(z.listen) or 'nothing'}")]
    out = []
    for ep in z.connect:
        proto, _, addr = ep.partition("/")
        host, _, port = addr.rpartition(":")
        if proto not in ("tcp", "tls") or not port.isdigit():
            out.append(Check("zenoh", WARN, f"{ep}: not probed ({proto})"))
            continue
        try:
            with socket.create_connection((host.strip("[]"), int(port)), timeout=1.0):
                pass
            out.append(Check("zenoh", OK, f"{ep} accepts connections"))
        except OSError as e:
            out.append(Check("zenoh", FAIL, f"{ep}: {e.strerror or e}",
                             "start the router (`nislam router`) or fix [zenoh] connect"))
    return out


def _disk(path: Path) -> Check:
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    free_gb = shutil.disk_usage(p).free / 1e9
    if free_gb < MIN_FREE_GB:
        return Check("disk", WARN, f"{free_gb:.1f} GB free at {p}",
                     f"free space (a 10-min recording takes ~{MIN_FREE_GB:g} GB)")
    return Check("disk", OK, f"{free_gb:.0f} GB free at {p}")


def _clock(now_s: float) -> Check:
    if now_s < EPOCH_2024:
        return Check("clock", WARN, time.strftime("wall clock reads %Y-%m-%d", time.gmtime(now_s)),
                     "no RTC and no NTP yet: enable systemd-timesyncd (stamps are monotonic "
                     "and unaffected; TLS certificates and file names are)")
    return Check("clock", OK, time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(now_s)))


def run_checks(cfg: Config, *, dai_loader: Callable[[], Any] | None = None,
               out_dir: Path = Path("results"), wait_s: float = 3.0,
               wall_clock: Callable[[], float] = time.time) -> list[Check]:
    """Every check, the device probes running at the same time."""
    from drivers.oak import import_depthai

    t0 = time.monotonic()
    src = cfg.ahrs.source
    pending: list[Callable[[], list[Check]]] = []
    pending.append(_camera(cfg, dai_loader or import_depthai, wait_s, imu=src == "oak_imu"))
    if src == "myahrs":
        pending.append(_myahrs(cfg, wait_s))
    if cfg.mavlink.enabled or src == "autopilot":
        pending.append(_mavlink(cfg, wait_s, need_attitude=src == "autopilot"))
    checks: list[Check] = []
    if src == "none":
        checks.append(Check("ahrs", WARN, "[ahrs] source = \"none\": FastORB only",
                            "set [ahrs] source for NI-SLAM"))
    checks += _zenoh(cfg) if cfg.zenoh.enabled else [Check("zenoh", SKIP, "[zenoh] off")]
    if not (cfg.mavlink.enabled or src == "autopilot"):
        checks.append(Check("mavlink", SKIP, "[mavlink] off"))
    checks += [_disk(out_dir), _clock(wall_clock())]
    # The devices need a moment to enumerate and stream (each result() then
    # measures its rate for up to 1 s more).
    time.sleep(max(0.0, wait_s - 1.0 - (time.monotonic() - t0)))
    for result in pending:
        checks[:0] = result()
    order = ["camera", "ahrs", "mavlink", "zenoh", "disk", "clock"]
    return sorted(checks, key=lambda c: next(i for i, k in enumerate(order)
                                             if c.name.startswith(k)))


def table(checks: list[Check]) -> str:
    w = max(len(c.name) for c in checks)
    lines = [f"{'check':<{w}}  {'':4}  detail"]
    for c in checks:
        lines.append(f"{c.name:<{w}}  {c.status:<4}  {c.detail}")
        if c.fix and c.status in (FAIL, WARN):
            lines.append(f"{'':<{w}}        fix: {c.fix}")
    return "\n".join(lines)


def add_doctor_parser(sub: Any, verbose: argparse.ArgumentParser) -> None:
    dp = sub.add_parser(
        "doctor", parents=[verbose], help="preflight check of the configured hardware",
        description="Probe once what the configuration names (camera, AHRS, MAVLink peer, "
                    "zenoh endpoints, disk, clock), print a table with a fix for each failure; "
                    "exit 1 when anything the service needs is missing.")
    dp.add_argument("--config", type=Path, metavar="FILE", help="TOML config (default: built-in)")
    dp.add_argument("--mavlink", metavar="URL", help="probe this MAVLink peer ([mavlink] connect)")
    dp.add_argument("--wait", type=float, default=3.0, metavar="S",
                    help="how long devices get to answer (default 3)")
    dp.set_defaults(func=cmd_doctor)


def cmd_doctor(args: argparse.Namespace) -> int:
    from onboard import NislamError
    from onboard.app.config import load_config

    if not 0.5 <= args.wait <= 60.0:
        raise NislamError(f"--wait must be in [0.5, 60], got {args.wait:g}")
    overrides = {"mavlink.connect": args.mavlink, "mavlink.enabled": True} if args.mavlink else {}
    cfg = load_config(args.config, overrides, overrides_origin="command line")
    # The drivers' own warnings would repeat the table's rows.
    drivers_log = logging.getLogger("drivers")
    level = drivers_log.level
    drivers_log.setLevel(logging.ERROR)
    try:
        checks = run_checks(cfg, wait_s=args.wait)
    finally:
        drivers_log.setLevel(level)
    print(table(checks))
    failed = [c.name for c in checks if c.status == FAIL]
    print(f"{len(failed)} of {len(checks)} checks failed: the service lacks "
          f"{', '.join(failed)}" if failed else "ready: nothing the service needs is missing")
    return 1 if failed else 0
