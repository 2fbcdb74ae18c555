"""The data commands: `nislam sim` (synthetic flights), `nislam faults`
(damaged copies), `nislam record` (the sensors into a recording) and
`nislam listen` (the ground side of zenoh).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

from onboard import NislamError
from onboard.app.cli_args import (
    MAX_RATE_HZ,
    MAX_RUN_S,
    SCENARIO_NAMES,
    attitude_error_args,
    check_range,
    config_arg,
    positive_int,
    stop_on_signals,
)

log = logging.getLogger("nislam")


def add_data_parsers(sub: Any, verbose: argparse.ArgumentParser) -> None:
    _add_listen_parser(sub, verbose)
    _add_record_parser(sub, verbose)
    _add_sim_parsers(sub, verbose)


FAULTS_HELP = """\
fault SPEC: comma-separated items KIND[:VALUE][@SECONDS]; @ places the fault that many
seconds after the first frame (a run of consecutive frames), otherwise faults land at
random frames / samples (fixed by --seed), never in the first second or the last half
second, at least 3 frames apart. Kinds (VALUE = count unless noted, default 1):
  drop:N          N frames missing (list lines and files left out)
  dup:N           N frames listed twice with the same stamp
  swap:N          N pairs of neighbouring frames listed in swapped order
  truncate:N      N colour images cut to half their size
  corrupt:N       N depth images with garbage inside (checksum fails)
  zero-depth:N    N depth images all zero
  att-gap:S       attitude samples missing for S seconds (S > 0.2, default 0.5)
  att-nan:N       N attitude samples written as NaN
  att-spike:N     N attitude samples turned 20-45 deg
  clock-jump:S    every stamp after a point moves S seconds later (S >= 1, default 2)
e.g. --faults drop:5,swap:2,att-gap:0.5@8,clock-jump:2
The copy's faults.json lists what was done and what the reader must count."""


def _add_sim_parsers(sub: Any, verbose: argparse.ArgumentParser) -> None:
    raw = argparse.RawDescriptionHelpFormatter
    sp = sub.add_parser(
        "sim", parents=[verbose], formatter_class=raw, epilog=FAULTS_HELP,
        help="fly a synthetic scenario, write an RGB-D + attitude recording",
        description="Render a synthetic flight (exact ground truth) into a TUM-layout folder\n"
                    "that `nislam replay` reads.\nScenarios: " + ", ".join(SCENARIO_NAMES) + ".")
    sp.add_argument("scenario", metavar="SCENARIO", help=", ".join(SCENARIO_NAMES))
    sp.add_argument("--seconds", type=float, default=20.0, metavar="N",
                    help="flight length (default 20)")
    sp.add_argument("--out", type=Path, metavar="DIR",
                    help="output folder (default: results/sim_<scenario>)")
    sp.add_argument("--seed", type=int, default=0, metavar="N",
                    help="seed of textures, sensor noise and faults (default 0)")
    sp.add_argument("--faults", metavar="SPEC", help="write a damaged recording (see below)")
    sp.add_argument("--camera-hz", type=float, default=30.0, metavar="X", help="default 30")
    sp.add_argument("--width", type=positive_int, default=640, metavar="PX",
                    help="image width (default 640; focal length scales with it)")
    sp.add_argument("--height", type=positive_int, default=480, metavar="PX",
                    help="image height (default 480)")
    sp.add_argument("--mount", choices=("forward", "down"), default="forward",
                    help="camera mount on the body (default forward)")
    sp.add_argument("--ideal-camera", action="store_true",
                    help="exact depth without noise or holes, no pixel noise")
    sp.add_argument("--ahrs-hz", type=float, default=100.0, metavar="X", help="default 100")
    sp.add_argument("--ahrs-profile", metavar="NAME",
                    help="AHRS error profile: perfect, myahrs, autopilot (sets the four below)")
    sp.add_argument("--depth-profile", metavar="NAME",
                    help="depth sensor: gaussian (default), kinect (disparity steps, "
                         "window-correlated noise)")
    attitude_error_args(sp)
    sp.add_argument("--attitude-dropout", type=float, metavar="P",
                    help="share of attitude samples lost, [0, 1) (default 0)")
    sp.add_argument("--quiet", action="store_true", help="no progress bar")
    sp.set_defaults(func=cmd_sim)

    fp = sub.add_parser(
        "faults", parents=[verbose], formatter_class=raw, epilog=FAULTS_HELP,
        help="write a damaged copy of a recording (synthetic or recorded)",
        description="Copy a TUM-layout recording with faults injected; the source is only read.")
    fp.add_argument("src", metavar="SEQ_DIR", type=Path, help="recording to damage")
    fp.add_argument("--out", type=Path, metavar="DIR", required=True, help="where the copy goes")
    fp.add_argument("--faults", metavar="SPEC", required=True, help="what to damage (see below)")
    fp.add_argument("--seed", type=int, default=0, metavar="N", help="placement seed (default 0)")
    fp.set_defaults(func=cmd_faults)


def cmd_sim(args: argparse.Namespace) -> int:
    from sim_replay.sim import sim_options, simulate

    opts = sim_options(
        seconds=args.seconds, seed=args.seed, camera_hz=args.camera_hz, ahrs_hz=args.ahrs_hz,
        width=args.width, height=args.height, mount=args.mount, ideal_camera=args.ideal_camera,
        ahrs_profile_name=args.ahrs_profile, attitude_noise_deg=args.attitude_noise_deg,
        attitude_bias_deg_per_sqrt_s=args.attitude_bias_deg_per_sqrt_s,
        attitude_offset_ms=args.attitude_offset_ms, attitude_dropout=args.attitude_dropout,
        depth_profile_name=args.depth_profile,
    )
    out_dir = args.out or Path("results") / f"sim_{args.scenario}"
    result = simulate(args.scenario, out_dir, opts, faults=args.faults, progress=not args.quiet)
    print("\n".join(result.summary_lines()))
    return 0


def cmd_faults(args: argparse.Namespace) -> int:
    from sim_replay.faults import inject_faults

    manifest = inject_faults(args.src, args.out, args.faults, seed=args.seed)
    expected = ", ".join(f"{k} +{v}" for k, v in manifest["expected"].items()) or "nothing"
    print(f"damaged copy of {args.src} in {args.out}: {manifest['spec']}")
    print(f"the reader should count (beyond the source's own): {expected}")
    return 0


# --------------------------------------------------------------------------- nislam listen


def _add_listen_parser(sub: Any, verbose: argparse.ArgumentParser) -> None:
    lp = sub.add_parser(
        "listen", parents=[verbose], help="ground side: print a vehicle's pose and status, "
        "fetch and follow its map",
        description="Subscribe to nislam/<vehicle>/{pose,status,map/**} over zenoh, fetch the "
                    "map the vehicle already has, keep it up to date and write it as PLY on "
                    "exit (Ctrl-C or SIGTERM).")
    lp.add_argument("--connect", action="append", metavar="ENDPOINT",
                    help="zenoh endpoint to connect to, e.g. tcp/192.168.1.10:7447 "
                         "(repeatable; default: [zenoh] connect)")
    lp.add_argument("--listen", action="append", metavar="ENDPOINT",
                    help="zenoh endpoint to listen on (repeatable; default: [zenoh] listen)")
    lp.add_argument("--mode", choices=("peer", "client"), help="zenoh mode (default: [zenoh] mode)")
    lp.add_argument("--vehicle", metavar="ID", help="vehicle id (default: [zenoh] vehicle)")
    lp.add_argument("--out", type=Path, metavar="FILE", help="write the map here as PLY on exit")
    config_arg(lp)
    lp.add_argument("--json", action="store_true",
                    help="print every message as one JSON line (type: ready, pose, status, "
                         "keyframe, map, saved)")
    lp.add_argument("--pose-hz", type=float, default=2.0, metavar="X",
                    help="print at most X pose lines per second (default 2; --json prints all)")
    lp.set_defaults(func=cmd_listen)


def cmd_listen(args: argparse.Namespace) -> int:
    check_range("--pose-hz", args.pose_hz, 0.0, MAX_RATE_HZ, lo_open=True)
    from onboard.app.config import load_config
    from onboard.outputs.listen import listen

    overrides: dict[str, Any] = {}
    for flag, key in (("connect", "zenoh.connect"), ("listen", "zenoh.listen"),
                      ("mode", "zenoh.mode"), ("vehicle", "zenoh.vehicle")):
        if getattr(args, flag) is not None:
            overrides[key] = getattr(args, flag)
    cfg = load_config(args.config, overrides, overrides_origin="command line")
    with stop_on_signals() as stop:
        result = listen(cfg.zenoh, stop, args.out, emit=lambda line: print(line, flush=True),
                        json_lines=args.json, pose_hz=args.pose_hz)
    log.info("received %d poses and %d status messages", result.poses, result.statuses)
    return 0


# --------------------------------------------------------------------------- nislam record


def _add_record_parser(sub: Any, verbose: argparse.ArgumentParser) -> None:
    rc = sub.add_parser(
        "record", parents=[verbose], help="record the sensors into a sequence folder",
        description="Record OAK-D colour + depth and the configured AHRS ([ahrs] source) into "
                    "the TUM sequence layout (rgb/, depth/, rgb.txt, depth.txt, attitude.txt, "
                    "camera.toml). Files are written whole, so a killed recorder leaves a "
                    "readable sequence. Stops after --seconds, at the end of --replay, or on "
                    "Ctrl-C / SIGTERM.")
    config_arg(rc)
    rc.add_argument("--out", type=Path, metavar="DIR", required=True,
                    help="output folder (new or empty)")
    rc.add_argument("--seconds", type=float, metavar="N", help="stop after N seconds")
    rc.add_argument("--replay", type=Path, metavar="SEQ_DIR",
                    help="read a recorded sequence through the replay drivers at real-time pace "
                         "instead of the hardware")
    rc.add_argument("--replay-speed", type=float, default=1.0, metavar="X",
                    help="pace of --replay: 1 = real time (default), 0.5 = half speed")
    rc.set_defaults(func=cmd_record)


def cmd_record(args: argparse.Namespace) -> int:
    from onboard.app.config import load_config
    from onboard.app.record import record

    check_range("--seconds", args.seconds, 0.0, MAX_RUN_S, lo_open=True)
    check_range("--replay-speed", args.replay_speed, 0.01, 100.0)
    if not 0.01 <= args.replay_speed <= 100.0:
        raise NislamError(f"--replay-speed must be in [0.01, 100], got {args.replay_speed}")
    cfg = load_config(args.config)
    with stop_on_signals() as stop:
        result = record(cfg, args.out, seconds=args.seconds, replay_dir=args.replay,
                        replay_speed=args.replay_speed, stop=stop)
    print("\n".join(result.summary_lines()), flush=True)
    return 0
