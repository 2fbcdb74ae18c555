"""Command-line pieces shared by the `nislam` commands: argument types, the
flags several commands take, and a stop event for the long-running ones.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import threading
from collections.abc import Iterator
from pathlib import Path

import onboard
from onboard import NislamError
from sim_replay.flights import SCENARIOS

SCENARIO_NAMES = tuple(SCENARIOS)  # one list: the simulator's own


def default_bench_sequence() -> Path:
    """The shared `tum_fr1_rpy`, expected beside the checkout: <repo>/../shared/data."""
    return Path(onboard.__file__).resolve().parents[1].parent / "shared/data/tum_fr1_rpy"


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


# Upper bounds on what a user can type: a typo (an extra zero, 1e8) must be a
# one-line error, not an hour of work or the kernel's out-of-memory kill.
MAX_RUN_S = 30 * 86400.0  # run / record / ground --seconds: a month of service
MAX_RATE_HZ = 1000.0


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


def check_range(flag: str, value: float | None, lo: float, hi: float, *,
                lo_open: bool = False) -> None:
    """One line (NislamError) unless `value` is None or a number in [lo, hi]
    ((lo, hi] with `lo_open`); NaN and infinities are out of range."""
    if value is None:
        return
    if (value > lo if lo_open else value >= lo) and value <= hi:
        return
    raise NislamError(f"{flag} must be in {'(' if lo_open else '['}{_num(lo)}, {_num(hi)}], "
                      f"got {_num(value)}")


def config_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, metavar="FILE", help="TOML config (default: built-in)")


def attitude_error_args(p: argparse.ArgumentParser) -> None:
    """The AHRS error model's flags (default 0: the attitude as recorded)."""
    p.add_argument("--attitude-noise-deg", type=float, metavar="X",
                   help="white attitude noise, per-axis std [deg] (default 0)")
    p.add_argument("--attitude-bias-deg-per-sqrt-s", type=float, metavar="X",
                   help="attitude bias random walk [deg/sqrt(s)] (default 0)")
    p.add_argument("--attitude-offset-ms", type=float, metavar="X",
                   help="attitude stamps late by X ms (default 0)")


@contextlib.contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
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
