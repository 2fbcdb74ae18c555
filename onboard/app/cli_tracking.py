"""The tracking commands: `nislam replay` (track a recording and score it),
`nislam bench` (time the tracker alone) and `nislam run` (the onboard service).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from onboard import NislamError
from onboard.app.cli_args import (
    MAX_RUN_S,
    SCENARIO_NAMES,
    attitude_error_args,
    check_range,
    config_arg,
    default_bench_sequence,
    positive_int,
    stop_on_signals,
)


def add_tracking_parsers(sub: Any, verbose: argparse.ArgumentParser) -> None:
    _add_replay_bench_parsers(sub, verbose)
    _add_run_parser(sub, verbose)


def _add_replay_bench_parsers(sub: Any, verbose: argparse.ArgumentParser) -> None:
    rp = sub.add_parser("replay", parents=[verbose], help="track a recorded sequence and score it",
                        description="Track a TUM-layout sequence; write trajectory, metrics, "
                                    "plot, map and the effective config into --out.")
    rp.add_argument("seq_dir", metavar="SEQ_DIR", type=Path, help="TUM-layout sequence folder")
    _add_common(rp)
    rp.add_argument("--out", type=Path, metavar="DIR",
                    help="output folder (default: results/<sequence folder name>)")
    attitude_error_args(rp)
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
    bp.add_argument("--repeat", type=positive_int, default=1, metavar="N",
                    help="passes over the frames, a fresh tracker each (default 1)")
    bp.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    bp.set_defaults(func=cmd_bench)


def _add_common(p: argparse.ArgumentParser) -> None:
    config_arg(p)
    p.add_argument("--tracker", metavar="NAME", help="tracker (nislam, fastorb, fused; default nislam)")
    p.add_argument("--max-frames", type=positive_int, metavar="N", help="stop after N frames")
    ba = p.add_mutually_exclusive_group()
    ba.add_argument("--local-ba", action="store_true", default=None,
                    help="FastORB with its back end (local mapping and BA; [fastorb] local_ba)")
    ba.add_argument("--no-local-ba", action="store_false", dest="local_ba",
                    help="FastORB without its back end, to measure what it gains")
    p.add_argument("--no-loop-closure", action="store_true",
                   help="FastORB without loop closing ([fastorb] loop_closure = false)")


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
    if getattr(args, "local_ba", None) is not None:
        out["fastorb.local_ba"] = args.local_ba
    if getattr(args, "no_loop_closure", False):
        out["fastorb.loop_closure"] = False
    return out


def cmd_replay(args: argparse.Namespace) -> int:
    from onboard.app.config import load_config
    from onboard.app.replay import replay

    cfg = load_config(args.config, _overrides(args), overrides_origin="command line")
    out_dir = args.out or Path("results") / args.seq_dir.resolve().name
    result = replay(args.seq_dir, cfg, out_dir, args.max_frames, progress=not args.quiet)
    print("\n".join(result.summary_lines()))
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from onboard.app.bench import bench
    from onboard.app.config import load_config

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
    if stats["cpu_ms_median"] is not None:  # thread CPU time: less inflated by other load
        cpu = [(label, stats[f"{kind}_frames_cpu_ms_median"])
               for kind, label in (("keyframe", "new key"), ("plain", "other"))]
        print(f"CPU time per frame: median {stats['cpu_ms_median']:.2f} ms, "
              f"p95 {stats['cpu_ms_p95']:.2f} ms; " + ", ".join(
                  f"{label} {ms:.2f} ms" for label, ms in cpu if ms is not None))
    if stats["deferred_ms_median"] is not None:  # finish_frame(): after the pose
        new_key = stats["keyframe_deferred_ms_median"]
        print(f"after the pose (finish_frame): median {stats['deferred_ms_median']:.2f} ms, "
              f"p95 {stats['deferred_ms_p95']:.2f} ms"
              + (f", new key {new_key:.2f} ms" if new_key is not None else ""))
    print("stages (p50 / p99 ms, n): " + ", ".join(
        f"{name} {st['p50']:.2f} / {st['p99']:.2f} ({st['n']})"
        for name, st in stats["stages_ms"].items() if st["n"]))
    if stats.get("parts_ms_median"):  # the fused tracker: each part's median and share
        total = sum(stats["parts_ms_median"].values())
        print("median by part: " + ", ".join(
            f"{part} {ms:.2f} ms ({100.0 * ms / total:.0f} %)"
            for part, ms in stats["parts_ms_median"].items()))
    if stats["backend_slices"]:
        print(f"back end (after the frames, apart): {stats['backend_slices']} slices, median "
              f"{stats['backend_slice_ms_median']:.2f} ms, p95 {stats['backend_slice_ms_p95']:.2f}"
              " ms")
    if stats["backend_keyframes"]:
        print(f"  local BA per key frame ({stats['backend_keyframes']}): median "
              f"{stats['backend_keyframe_ms_median']:.1f} ms, p95 "
              f"{stats['backend_keyframe_ms_p95']:.1f} ms")
    if stats["loop_queries"]:
        fixed = (f"; {stats['loop_corrections']} corrections, median "
                 f"{stats['loop_correction_ms_median']:.1f} ms" if stats["loop_corrections"] else "")
        print(f"  loop closing per key frame ({stats['loop_queries']}): median "
              f"{stats['loop_query_ms_median']:.1f} ms, p95 {stats['loop_query_ms_p95']:.1f} ms"
              + fixed)
    return 0


# --------------------------------------------------------------------------- nislam run


def _add_run_parser(sub: Any, verbose: argparse.ArgumentParser) -> None:
    rn = sub.add_parser(
        "run", parents=[verbose], help="the onboard service: sensors -> tracker -> MAVLink/zenoh",
        description="Run the tracking loop on the configured hardware, or on a recorded "
                    "(--replay) or synthetic (--sim) flight replayed at its own pace through "
                    "the same drivers. Prints a statistics line every [service] stats_period_s "
                    "and a summary at the end (with ATE when the flight has ground truth). "
                    "SIGTERM / Ctrl-C: finish the frame, flush the outputs, exit 0.")
    config_arg(rn)
    rn.add_argument("--mavlink", metavar="URL",
                    help="send the vision feed here (pymavlink connection string, e.g. "
                         "udpout:127.0.0.1:14550); enables [mavlink]")
    rn.add_argument("--zenoh-connect", action="append", metavar="EP",
                    help="zenoh endpoint to connect to (repeatable); enables [zenoh]")
    rn.add_argument("--zenoh-listen", action="append", metavar="EP",
                    help="zenoh endpoint to listen on (repeatable); enables [zenoh]")
    rn.add_argument("--zenoh-mode", choices=("peer", "client"),
                    help="zenoh mode ([zenoh] mode; client: of a fleet router, docs/fleet.md)")
    rn.add_argument("--vehicle", metavar="ID", help="zenoh vehicle id ([zenoh] vehicle)")
    rn.add_argument("--tracker", metavar="NAME", help="tracker (fused, nislam, fastorb; default fused)")
    rn.add_argument("--no-loop-closure", action="store_true",
                    help="FastORB without loop closing ([fastorb] loop_closure = false)")
    src = rn.add_mutually_exclusive_group()
    src.add_argument("--replay", type=Path, metavar="SEQ_DIR",
                     help="replay a recording at real-time pace instead of the hardware")
    src.add_argument("--sim", metavar="SCENARIO",
                     help="generate a synthetic flight (" + ", ".join(SCENARIO_NAMES) + ") "
                          "and replay it")
    src.add_argument("--sim-follow", metavar="SCENE",
                     help="closed loop with a simulator on the --mavlink link (ArduPilot SITL): "
                          "render the camera and AHRS from the vehicle's true state (SIM_STATE) "
                          "in a synthetic scene (room, corridor, or a flight's start)")
    rn.add_argument("--ahrs-profile", metavar="NAME",
                    help="--sim-follow: simulated AHRS error (perfect, myahrs, autopilot)")
    rn.add_argument("--camera-size", metavar="WxH",
                    help="--sim-follow: rendered image size (default 640x480)")
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
    if args.no_loop_closure:
        out["fastorb.loop_closure"] = False
    if args.mavlink is not None:
        out.update({"mavlink.connect": args.mavlink, "mavlink.enabled": True})
    if args.zenoh_connect is not None:
        out.update({"zenoh.connect": args.zenoh_connect, "zenoh.enabled": True})
    if args.zenoh_listen is not None:
        out.update({"zenoh.listen": args.zenoh_listen, "zenoh.enabled": True})
    if args.zenoh_mode is not None:
        out["zenoh.mode"] = args.zenoh_mode
    if args.vehicle is not None:
        out["zenoh.vehicle"] = args.vehicle
    if args.ahrs_profile is not None:
        out["sim_follow.ahrs_profile"] = args.ahrs_profile
    if args.camera_size is not None:
        w, _, h = args.camera_size.lower().partition("x")
        if not (w.isdigit() and h.isdigit()):
            raise NislamError(f"--camera-size must look like 640x480, got {args.camera_size!r}")
        out.update({"sim_follow.width": int(w), "sim_follow.height": int(h)})
    return out


def cmd_run(args: argparse.Namespace) -> int:
    from onboard.app.config import load_config
    from onboard.app.sdnotify import Notifier
    from onboard.app.service import Service
    from onboard.app.sources import follow_sources, hardware_sources, replay_sources

    check_range("--seconds", args.seconds, 0.0, MAX_RUN_S, lo_open=True)
    if args.loop and (args.seconds is None or (args.replay is None and args.sim is None)):
        raise NislamError("--loop needs --seconds and --replay or --sim")
    if (args.ahrs_profile or args.camera_size) and args.sim_follow is None:
        raise NislamError("--ahrs-profile and --camera-size go with --sim-follow")
    cfg = load_config(args.config, _run_overrides(args), overrides_origin="command line")
    if args.sim_follow is not None and not cfg.mavlink.enabled:
        raise NislamError("--sim-follow needs the simulator's MAVLink link: --mavlink URL "
                          "(e.g. tcp:127.0.0.1:5762 for ArduPilot SITL)")
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
    elif args.sim_follow is not None:
        out_dir = out_dir or Path("results") / f"run_follow_{args.sim_follow}"
        sources = follow_sources(cfg, args.sim_follow)
    elif args.replay is not None:
        out_dir = out_dir or Path("results") / f"run_{args.replay.resolve().name}"
        sources, cfg = replay_sources(cfg, args.replay, loop_s)
    else:
        sources = hardware_sources(cfg)
    with stop_on_signals() as stop:
        service = Service(cfg, sources, stop, seconds=seconds, notifier=Notifier(),
                          emit=lambda line: print(line, flush=True), out_dir=out_dir,
                          realtime=True)
        result = service.run()
    print("\n".join(result.summary_lines()), flush=True)
    return 0
