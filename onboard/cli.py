"""The `nislam` command: `nislam replay` and `nislam bench`.

Parsing comes first and imports nothing heavy, so `--help` and usage errors
are instant; numpy, OpenCV and the tracker load only once a command runs.
Error policy: NislamError -> one line and exit 1; Ctrl-C -> exit 130;
anything else -> logged traceback and exit 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
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
    return parser


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
    kf = stats["keyframe_frames_ms_median"]
    print(f"{stats['sequence']}: {stats['tracker']}, {stats['frames']} frames x {stats['repeat']}")
    print(f"per frame: median {stats['frame_ms_median']:.2f} ms, "
          f"p95 {stats['frame_ms_p95']:.2f} ms, max {stats['frame_ms_max']:.2f} ms "
          f"-> {stats['hz']:.0f} Hz")
    if kf is not None:
        print(f"key-frame frames: {stats['keyframe_frames']}, median {kf:.2f} ms")
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
