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

SCENARIO_NAMES = ("hover", "circle", "figure8", "corridor", "yaw-spin", "aggressive", "blank-turn")


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
