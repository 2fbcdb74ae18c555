"""The `nislam` command: `nislam run` (the onboard service), `replay`, `bench`,
`sim`, `faults`, `listen` and `record`.

Parsing comes first and imports nothing heavy, so `--help` and usage errors
are instant; numpy, OpenCV and the tracker load only once a command runs.
Error policy: NislamError -> one line and exit 1; Ctrl-C -> exit 130;
anything else -> logged traceback and exit 2.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import onboard
from onboard import NislamError

log = logging.getLogger("nislam")

EXIT_ERROR = 1
EXIT_BUG = 2
EXIT_INTERRUPTED = 130


def default_bench_sequence() -> Path:
    """The shared `tum_fr1_rpy`, expected beside the checkout: <repo>/../shared/data."""
    return Path(onboard.__file__).resolve().parents[1].parent / "shared/data/tum_fr1_rpy"


# --------------------------------------------------------------------------- parser


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    # -v works before or after the subcommand. The action object is shared by
    # all parsers, so its default must stay SUPPRESS (a default of 0 would let
    # the subparser reset a count given before it); main() reads it with getattr.
    verbose = argparse.ArgumentParser(add_help=False)
    verbose.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS,
                         help="more log output on stderr (-v info, -vv debug)")
    parser = argparse.ArgumentParser(
        prog="nislam", parents=[verbose],
        description="NI-SLAM indoor positioning: replay recorded RGB-D data, "
                    "benchmark the tracker.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    rp = sub.add_parser("replay", parents=[verbose], help="track a recorded sequence and score it",
                        description="Track a TUM-layout sequence; write trajectory, metrics, "
                                    "plot, map and the effective config into --out.")
    rp.add_argument("seq_dir", metavar="SEQ_DIR", type=Path, help="TUM-layout sequence folder")
    _add_common(rp)
    rp.add_argument("--out", type=Path, metavar="DIR",
                    help="output folder (default: results/<sequence folder name>)")
    rp.add_argument("--attitude-noise-deg", type=float, metavar="X",
                    help="white attitude noise, per-axis std [deg]")
    rp.add_argument("--attitude-bias-deg-per-sqrt-s", type=float, metavar="X",
                    help="attitude bias random walk [deg/sqrt(s)]")
    rp.add_argument("--attitude-offset-ms", type=float, metavar="X",
                    help="attitude time offset [ms] (stamps late by X)")
    rp.add_argument("--seed", type=int, metavar="N", help="seed of the attitude error model")
    rp.add_argument("--no-attitude-calibration", action="store_true",
                    help="do not estimate the attitude time offset online")
    rp.add_argument("--quiet", action="store_true", help="no progress bar")
    rp.set_defaults(func=cmd_replay)

    bp = sub.add_parser("bench", parents=[verbose], help="time track() on frames in memory",
                        description="Time tracker.track() alone on decoded, undistorted frames.")
    bp.add_argument("seq_dir", metavar="SEQ_DIR", type=Path, nargs="?",
                    help=f"sequence folder (default: {default_bench_sequence()})")
    _add_common(bp)
    bp.add_argument("--repeat", type=_positive_int, default=1, metavar="N",
                    help="passes over the frames, a fresh tracker each (default 1)")
    bp.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    bp.set_defaults(func=cmd_bench)
    _add_run_parser(sub, verbose)
    _add_listen_parser(sub, verbose)
    _add_record_parser(sub, verbose)
    _add_sim_parsers(sub, verbose)
    return parser


# --------------------------------------------------------------------------- nislam sim / faults

SCENARIO_NAMES = ("hover", "circle", "figure8", "corridor", "yaw-spin", "aggressive")
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
    sp.add_argument("--width", type=_positive_int, default=640, metavar="PX",
                    help="image width (default 640; focal length scales with it)")
    sp.add_argument("--height", type=_positive_int, default=480, metavar="PX",
                    help="image height (default 480)")
    sp.add_argument("--mount", choices=("forward", "down"), default="forward",
                    help="camera mount on the body (default forward)")
    sp.add_argument("--ideal-camera", action="store_true",
                    help="exact depth without noise or holes, no pixel noise")
    sp.add_argument("--ahrs-hz", type=float, default=100.0, metavar="X", help="default 100")
    sp.add_argument("--ahrs-profile", metavar="NAME",
                    help="AHRS error profile: perfect, myahrs, autopilot (sets the four below)")
    sp.add_argument("--attitude-noise-deg", type=float, metavar="X",
                    help="white attitude noise, per-axis std [deg] (default 0)")
    sp.add_argument("--attitude-bias-deg-per-sqrt-s", type=float, metavar="X",
                    help="attitude bias random walk [deg/sqrt(s)] (default 0)")
    sp.add_argument("--attitude-offset-ms", type=float, metavar="X",
                    help="attitude stamps late by X ms (default 0)")
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


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, metavar="FILE", help="TOML config (default: built-in)")
    p.add_argument("--tracker", metavar="NAME", help="tracker (nislam, fastorb)")
    p.add_argument("--max-frames", type=_positive_int, metavar="N", help="stop after N frames")


def _overrides(args: argparse.Namespace) -> dict[str, Any]:
    """Flags given on the command line, as qualified config keys."""
    flags = {
        "tracker": "tracker.name",
        "attitude_noise_deg": "attitude.noise_deg",
        "attitude_bias_deg_per_sqrt_s": "attitude.bias_deg_per_sqrt_s",
        "attitude_offset_ms": "attitude.offset_ms",
        "seed": "attitude.seed",
    }
    out = {key: getattr(args, a) for a, key in flags.items() if getattr(args, a, None) is not None}
    if getattr(args, "no_attitude_calibration", False):
        out["nislam.calibrate_time_offset"] = False
    return out


# --------------------------------------------------------------------------- commands


def cmd_replay(args: argparse.Namespace) -> int:
    from onboard.config import load_config
    from onboard.replay import replay

    cfg = load_config(args.config, _overrides(args), overrides_origin="command line")
    out_dir = args.out or Path("results") / args.seq_dir.resolve().name
    result = replay(args.seq_dir, cfg, out_dir, args.max_frames, progress=not args.quiet)
    print("\n".join(result.summary_lines()))
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from onboard.bench import bench
    from onboard.config import load_config

    seq_dir = args.seq_dir
    if seq_dir is None:
        seq_dir = default_bench_sequence()
        if not seq_dir.is_dir():
            raise NislamError(
                f"no SEQ_DIR given and the default sequence {seq_dir} is absent "
                f"(the shared data belong beside the checkout: <repo>/../shared/data)"
            )
    cfg = load_config(args.config, _overrides(args), overrides_origin="command line")
    stats = bench(seq_dir, cfg, args.max_frames, args.repeat)
    if args.json:
        print(json.dumps(stats, allow_nan=False))
        return 0
    print(f"{stats['sequence']}: {stats['tracker']}, {stats['frames']} frames x {stats['repeat']}")
    print(f"per frame: median {stats['frame_ms_median']:.2f} ms, "
          f"p95 {stats['frame_ms_p95']:.2f} ms, max {stats['frame_ms_max']:.2f} ms "
          f"-> {stats['hz']:.0f} Hz")
    kinds = [(label, stats[f"{kind}_frames"], stats[f"{kind}_frames_ms_median"])
             for kind, label in (("keyframe", "new key"), ("reused", "key re-used"),
                                 ("plain", "other"))]
    print("median by frame kind: " + ", ".join(
        f"{label} {ms:.2f} ms ({n})" for label, n, ms in kinds if ms is not None))
    return 0


# --------------------------------------------------------------------------- nislam run


@contextlib.contextmanager
def _stop_on_signals() -> Iterator[threading.Event]:
    """An Event that SIGINT and SIGTERM set (the long-running commands stop
    cleanly on either); the previous handlers come back afterwards."""
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set())
                for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _add_run_parser(sub: Any, verbose: argparse.ArgumentParser) -> None:
    rn = sub.add_parser(
        "run", parents=[verbose], help="the onboard service: sensors -> tracker -> MAVLink/zenoh",
        description="Run the tracking loop on the configured hardware, or on a recorded "
                    "(--replay) or synthetic (--sim) flight replayed at its own pace through "
                    "the same drivers. Prints a statistics line every [service] stats_period_s "
                    "and a summary at the end (with ATE when the flight has ground truth). "
                    "SIGTERM / Ctrl-C: finish the frame, flush the outputs, exit 0.")
    rn.add_argument("--config", type=Path, metavar="FILE", help="TOML config (default: built-in)")
    rn.add_argument("--mavlink", metavar="URL",
                    help="send the vision feed here (pymavlink connection string, e.g. "
                         "udpout:127.0.0.1:14550); enables [mavlink]")
    rn.add_argument("--zenoh-connect", action="append", metavar="EP",
                    help="zenoh endpoint to connect to (repeatable); enables [zenoh]")
    rn.add_argument("--zenoh-listen", action="append", metavar="EP",
                    help="zenoh endpoint to listen on (repeatable); enables [zenoh]")
    rn.add_argument("--vehicle", metavar="ID", help="zenoh vehicle id ([zenoh] vehicle)")
    rn.add_argument("--tracker", metavar="NAME", help="primary tracker (nislam, fastorb)")
    src = rn.add_mutually_exclusive_group()
    src.add_argument("--replay", type=Path, metavar="SEQ_DIR",
                     help="replay a recording at real-time pace instead of the hardware")
    src.add_argument("--sim", metavar="SCENARIO",
                     help="generate a synthetic flight (" + ", ".join(SCENARIO_NAMES) + ") "
                          "and replay it")
    rn.add_argument("--seconds", type=float, metavar="N",
                    help="stop after N seconds (with --sim: the flight's length, default 20)")
    rn.add_argument("--loop", action="store_true",
                    help="with --replay / --sim and --seconds: play the flight forwards and "
                         "backwards in turn until --seconds have passed (soak runs)")
    rn.add_argument("--seed", type=int, default=0, metavar="N", help="--sim seed (default 0)")
    rn.add_argument("--out", type=Path, metavar="DIR",
                    help="write trajectory, metrics and config here (default with --replay / "
                         "--sim: results/run_<name>; on hardware: nothing)")
    rn.set_defaults(func=cmd_run)


def _run_overrides(args: argparse.Namespace) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if args.tracker is not None:
        out["tracker.name"] = args.tracker
    if args.mavlink is not None:
        out.update({"mavlink.connect": args.mavlink, "mavlink.enabled": True})
    if args.zenoh_connect is not None:
        out.update({"zenoh.connect": args.zenoh_connect, "zenoh.enabled": True})
    if args.zenoh_listen is not None:
        out.update({"zenoh.listen": args.zenoh_listen, "zenoh.enabled": True})
    if args.vehicle is not None:
        out["zenoh.vehicle"] = args.vehicle
    return out


def cmd_run(args: argparse.Namespace) -> int:
    from onboard.config import load_config
    from onboard.sdnotify import Notifier
    from onboard.service import Service, hardware_sources, replay_sources

    if args.seconds is not None and not args.seconds > 0:
        raise NislamError(f"--seconds must be > 0, got {args.seconds}")
    if args.loop and (args.seconds is None or (args.replay is None and args.sim is None)):
        raise NislamError("--loop needs --seconds and --replay or --sim")
    cfg = load_config(args.config, _run_overrides(args), overrides_origin="command line")
    out_dir, seconds = args.out, args.seconds
    loop_s = seconds if args.loop else None
    if args.sim is not None:
        from sim_replay.sim import SimOptions, simulate

        out_dir = out_dir or Path("results") / f"run_sim_{args.sim}"
        flight_s = 20.0 if args.loop or seconds is None else seconds
        flight = simulate(args.sim, out_dir / "flight", SimOptions(seconds=flight_s, seed=args.seed),
                          progress=True)
        print("\n".join(flight.summary_lines()), flush=True)
        sources, cfg = replay_sources(cfg, flight.out_dir, loop_s)
        if not args.loop:
            seconds = None  # the replay ends with the flight
    elif args.replay is not None:
        out_dir = out_dir or Path("results") / f"run_{args.replay.resolve().name}"
        sources, cfg = replay_sources(cfg, args.replay, loop_s)
    else:
        sources = hardware_sources(cfg)
    with _stop_on_signals() as stop:
        service = Service(cfg, sources, stop, seconds=seconds, notifier=Notifier(),
                          emit=lambda line: print(line, flush=True), out_dir=out_dir)
        result = service.run()
    print("\n".join(result.summary_lines()), flush=True)
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
    lp.add_argument("--config", type=Path, metavar="FILE", help="TOML config (default: built-in)")
    lp.add_argument("--json", action="store_true",
                    help="print every message as one JSON line (type: ready, pose, status, "
                         "keyframe, map, saved)")
    lp.add_argument("--pose-hz", type=float, default=2.0, metavar="X",
                    help="print at most X pose lines per second (default 2; --json prints all)")
    lp.set_defaults(func=cmd_listen)


def cmd_listen(args: argparse.Namespace) -> int:
    from onboard.config import load_config
    from onboard.listen import listen

    overrides: dict[str, Any] = {}
    for flag, key in (("connect", "zenoh.connect"), ("listen", "zenoh.listen"),
                      ("mode", "zenoh.mode"), ("vehicle", "zenoh.vehicle")):
        if getattr(args, flag) is not None:
            overrides[key] = getattr(args, flag)
    cfg = load_config(args.config, overrides, overrides_origin="command line")
    with _stop_on_signals() as stop:
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
    rc.add_argument("--config", type=Path, metavar="FILE", help="TOML config (default: built-in)")
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
    from drivers.recorder import record
    from onboard.config import load_config

    if args.seconds is not None and not args.seconds > 0:
        raise NislamError(f"--seconds must be > 0, got {args.seconds}")
    if not 0.01 <= args.replay_speed <= 100.0:
        raise NislamError(f"--replay-speed must be in [0.01, 100], got {args.replay_speed}")
    cfg = load_config(args.config)
    with _stop_on_signals() as stop:
        result = record(cfg, args.out, seconds=args.seconds, replay_dir=args.replay,
                        replay_speed=args.replay_speed, stop=stop)
    print("\n".join(result.summary_lines()), flush=True)
    return 0


# --------------------------------------------------------------------------- entry point


class _Formatter(logging.Formatter):
    """`nislam: warning: message`; with -vv the logger name too."""

    def __init__(self, with_names: bool) -> None:
        super().__init__()
        self.with_names = with_names

    def format(self, record: logging.LogRecord) -> str:
        text = record.getMessage()
        if self.with_names:
            text = f"{record.name}: {text}"
        line = f"nislam: {record.levelname.lower()}: {text}"
        if record.exc_info:
            line += "\n" + self.formatException(record.exc_info)
        return line


def configure_logging(verbosity: int) -> None:
    level = logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_Formatter(with_names=verbosity >= 2))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
    # Third-party debug chatter (matplotlib font search, PIL) drowns our own.
    for noisy in ("matplotlib", "PIL"):
        logging.getLogger(noisy).setLevel(max(level, logging.INFO))


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(getattr(args, "verbose", 0))
    try:
        return args.func(args)
    except NislamError as e:
        log.error("%s", " ".join(str(e).split("\n")))
        return EXIT_ERROR
    except KeyboardInterrupt:
        log.error("interrupted")
        return EXIT_INTERRUPTED
    except Exception:
        log.exception("unexpected error (a bug; please report it with this traceback)")
        return EXIT_BUG


if __name__ == "__main__":
    sys.exit(main())
