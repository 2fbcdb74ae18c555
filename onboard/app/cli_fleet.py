"""The fleet commands: `nislam router` (a zenoh router for vehicles and
ground stations) and `nislam ground` (the ground station: every vehicle's
status, map and trajectory). docs/fleet.md.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import signal
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from onboard import NislamError
from onboard.app.cli_args import MAX_RUN_S, check_range, config_arg, stop_on_signals

log = logging.getLogger("nislam")


def add_fleet_parsers(sub: Any, verbose: argparse.ArgumentParser) -> None:
    rp = sub.add_parser(
        "router", parents=[verbose], help="a zenoh router for the fleet",
        description="Run a zenoh router (zenoh's router mode) configured from [router]: "
                    "vehicles and ground stations connect to it; with TLS and acl, only "
                    "holders of a fleet certificate, each vehicle under its own keys. "
                    "SIGTERM / Ctrl-C stop it.")
    rp.add_argument("--listen", action="append", metavar="EP",
                    help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 or tls/0.0.0.0:7447 "
                         "(repeatable; default: [router] listen)")
    rp.add_argument("--connect", action="append", metavar="EP",
                    help="another router to join (repeatable; default: [router] connect)")
    config_arg(rp)
    rp.add_argument("--print-config", action="store_true",
                    help="print the zenoh configuration as JSON (for zenohd -c) and exit")
    rp.set_defaults(func=cmd_router)

    gp = sub.add_parser(
        "ground", parents=[verbose], help="the fleet's ground station",
        description="Follow every vehicle under nislam/*/ : a live one-line-per-vehicle "
                    "table, each vehicle's map (fetched when it is discovered and whenever "
                    "its status says ours differs), a fleet status queryable "
                    "(nislam/@fleet/status). On exit (--seconds, Ctrl-C, SIGTERM) and on "
                    "SIGUSR1 it writes DIR/fleet.json, DIR/<id>.ply and DIR/fleet.png.")
    gp.add_argument("--connect", action="append", metavar="EP",
                    help="router endpoint (repeatable; default: [zenoh] connect)")
    gp.add_argument("--mode", choices=("client", "peer"), default="client",
                    help="zenoh mode (default client)")
    gp.add_argument("--out", type=Path, metavar="DIR", required=True, help="output folder")
    gp.add_argument("--seconds", type=float, metavar="N", help="stop after N seconds")
    gp.add_argument("--table-period", type=float, default=1.0, metavar="S",
                    help="print the table every S seconds (default 1; 0: never)")
    config_arg(gp)
    gp.set_defaults(func=cmd_ground)


def cmd_router(args: argparse.Namespace) -> int:
    from onboard.app.config import load_config
    from onboard.outputs.router import router_json, run_router

    overrides: dict[str, Any] = {}
    if args.listen is not None:
        overrides["router.listen"] = args.listen
    if args.connect is not None:
        overrides["router.connect"] = args.connect
    cfg = load_config(args.config, overrides, overrides_origin="command line").router
    if args.print_config:
        print(router_json(cfg))
        return 0
    with stop_on_signals() as stop:
        run_router(cfg, stop, on_ready=lambda zid: print(
            f"router {zid} listening on {', '.join(cfg.listen)}", flush=True))
    return 0


@contextlib.contextmanager
def _save_on_sigusr1() -> Iterator[threading.Event]:
    save = threading.Event()
    previous = signal.signal(signal.SIGUSR1, lambda *_: save.set())
    try:
        yield save
    finally:
        signal.signal(signal.SIGUSR1, previous)


def cmd_ground(args: argparse.Namespace) -> int:
    from onboard.app.config import load_config
    from onboard.outputs.ground import GroundStation, run_ground
    from onboard.outputs.zenoh_session import open_waiting, session_config

    check_range("--seconds", args.seconds, 0.0, MAX_RUN_S, lo_open=True)
    check_range("--table-period", args.table_period, 0.0, 3600.0)
    overrides: dict[str, Any] = {"zenoh.mode": args.mode}
    if args.connect is not None:
        overrides["zenoh.connect"] = args.connect
    cfg = load_config(args.config, overrides, overrides_origin="command line").zenoh
    if not cfg.connect:
        raise NislamError("no router to connect to: give --connect EP (or [zenoh] connect)")
    if args.table_period < 0:
        raise NislamError(f"--table-period must be >= 0, got {args.table_period}")
    with stop_on_signals() as stop, _save_on_sigusr1() as save:
        session = open_waiting(session_config(cfg, listen=()), stop, on_wait=lambda: log.warning(
            "waiting for the router at %s", ", ".join(cfg.connect)))
        if session is None:
            return 0
        try:
            station = GroundStation(session)
            try:
                result = run_ground(station, args.out, stop, args.seconds,
                                    lambda line: print(line, flush=True), args.table_period, save)
            finally:
                station.close()
        finally:
            session.close()
    n = len(result.summary["vehicles"])
    print(json.dumps({"vehicles": n, "files": [str(p) for p in result.files]}), flush=True)
    return 0
