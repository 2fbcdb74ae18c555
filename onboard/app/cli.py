"""The `nislam` command: `nislam run` (the onboard service), `replay`, `bench`,
`sim`, `faults`, `listen`, `record`, and the fleet's `router` and `ground`.

Parsing comes first and imports nothing heavy, so `--help` and usage errors
are instant; numpy, OpenCV and the tracker load only once a command runs.
Error policy: NislamError -> one line and exit 1; Ctrl-C -> exit 130;
anything else -> logged traceback and exit 2.
"""

from __future__ import annotations

import argparse
import logging
import sys

from onboard import NislamError
from onboard.app.cli_data import add_data_parsers
from onboard.app.cli_fleet import add_fleet_parsers
from onboard.app.cli_tracking import add_tracking_parsers
from onboard.app.doctor import add_doctor_parser

log = logging.getLogger("nislam")

EXIT_ERROR = 1
EXIT_BUG = 2
EXIT_INTERRUPTED = 130


def build_parser() -> argparse.ArgumentParser:
    # -v works before or after the subcommand. The action object is shared by
    # all parsers, so its default must stay SUPPRESS (a default of 0 would let
    # the subparser reset a count given before it); main() reads it with getattr.
    verbose = argparse.ArgumentParser(add_help=False)
    verbose.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS,
                         help="more log output on stderr (-v info, -vv debug)")
    parser = argparse.ArgumentParser(
        prog="nislam", parents=[verbose],
        description="Indoor drone positioning from RGB-D + attitude: the onboard service, "
                    "replays, benchmarks, synthetic flights and recordings.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    add_tracking_parsers(sub, verbose)
    add_data_parsers(sub, verbose)
    add_fleet_parsers(sub, verbose)
    add_doctor_parser(sub, verbose)
    return parser


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
