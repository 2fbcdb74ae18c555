"""The issue-21 flight in ArduPilot SITL, scored by the simulator's truth.

    # SITL with the shipped parameters, without MAVProxy on its console port:
    sim_vehicle.py -v ArduCopter --add-param-file=config/ardupilot-extnav.parm --no-mavproxy
    .venv/bin/python scripts/sitl_acceptance.py --gcs tcp:127.0.0.1:5760 \
        --nislam ".venv/bin/nislam run --sim-follow room --mavlink tcp:127.0.0.1:5762"

Plays the ground station on `--gcs`: starts `--nislam` (the service on
SITL's second port), waits until the EKF has a position from the feed, sets
GUIDED, arms, takes off to `--alt-m`, settles, holds `--hold-s` (60 s) and
records the true horizontal drift; moves `--move-m` (2 m) north with
SET_POSITION_TARGET_LOCAL_NED and records how far from its target the
vehicle ends, by truth; then restarts the service during a hover (SIGTERM,
start again) and records how far the vehicle moves; lands. Truth is SIM_STATE
(requested here at 50 Hz), metres from lat/lon as ArduPilot converts them.
Writes `--out`/sitl_acceptance.json and prints the three figures against the
bars (drift <= 0.15 m, move error <= 0.1 m, restart <= 0.2 m).

Not run in this project's CI (no SITL here): the review runs it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sim_replay.follow_state import Anchor, state_from_message  # noqa: E402

GUIDED, LAND = 4, 9  # ArduCopter custom modes
MAV_CMD_DO_SET_MODE, MAV_CMD_ARM, MAV_CMD_TAKEOFF, MAV_CMD_INTERVAL = 176, 400, 22, 511
EKF_POS_HORIZ_REL, EKF_CONST_POS_MODE = 8, 128
POSITION_ONLY = 0b110111111000  # SET_POSITION_TARGET_LOCAL_NED: use x, y, z only


class Gcs:
    def __init__(self, url: str, target: int) -> None:
        os.environ["MAVLINK20"] = "1"
        from pymavlink import mavutil

        self.conn = mavutil.mavlink_connection(url, source_system=255, source_component=190)
        self.target = target
        self.anchor: Anchor | None = None
        self.truth: list[tuple[float, float, float, float]] = []  # t, n, e, d
        self.local: tuple[float, float, float] | None = None
        self.ekf_flags = 0
        self.texts: list[str] = []

    def command(self, cmd: int, *params: float) -> None:
        p = list(params) + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(self.target, 1, cmd, 0, *p)

    def pump(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            msg = self.conn.recv_match(blocking=True, timeout=0.05)
            if msg is None:
                continue
            kind = msg.get_type()
            if kind in ("SIM_STATE",):
                s = state_from_message(msg, time.monotonic_ns())
                if s is not None:
                    self.anchor = self.anchor or Anchor(s.lat_e7, s.lon_e7, s.alt_m)
                    n, e, d = self.anchor.ned_m(s)
                    self.truth.append((time.monotonic(), n, e, d))
            elif kind == "LOCAL_POSITION_NED" and msg.get_srcComponent() == 1:
                self.local = (msg.x, msg.y, msg.z)
            elif kind == "EKF_STATUS_REPORT":
                self.ekf_flags = msg.flags
            elif kind == "STATUSTEXT":
                text = msg.text if isinstance(msg.text, str) else msg.text.decode("ascii", "replace")
                self.texts.append(text)
                print(f"  [{msg.get_srcComponent()}] {text}", flush=True)

    def wait(self, what: str, pred, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while not pred():
            if time.monotonic() > end:
                raise SystemExit(f"timed out waiting for {what}")
            self.pump(0.2)

    def here(self) -> tuple[float, float, float]:
        _t, n, e, d = self.truth[-1]
        return n, e, d


def horizontal(a, b) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])


def track(gcs: Gcs, seconds: float, ref) -> tuple[float, float]:
    """(max, final) true horizontal distance from `ref` over `seconds`."""
    start = len(gcs.truth)
    gcs.pump(seconds)
    d = [horizontal((n, e), ref) for _t, n, e, _d in gcs.truth[start:]]
    return max(d), d[-1]


def start_nislam(cmd: str, log_path: Path) -> subprocess.Popen:
    log = open(log_path, "ab")  # noqa: SIM115 - kept open for the child's life
    return subprocess.Popen(shlex.split(cmd), stdout=log, stderr=subprocess.STDOUT)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gcs", default="tcp:127.0.0.1:5760", help="SITL's console port")
    ap.add_argument("--nislam", required=True, help="the service's command line")
    ap.add_argument("--target-system", type=int, default=1)
    ap.add_argument("--alt-m", type=float, default=1.0)
    ap.add_argument("--hold-s", type=float, default=60.0)
    ap.add_argument("--move-m", type=float, default=2.0)
    ap.add_argument("--out", type=Path, default=Path("results/sitl_acceptance"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    gcs = Gcs(args.gcs, args.target_system)
    gcs.conn.wait_heartbeat(timeout=60)
    for msg_id, hz in ((108, 50), (32, 10), (193, 5)):  # SIM_STATE, LOCAL_POSITION_NED, EKF_STATUS
        gcs.command(MAV_CMD_INTERVAL, msg_id, 1e6 / hz)
    svc = start_nislam(args.nislam, args.out / "nislam.log")
    result: dict = {}
    try:
        gcs.wait("truth", lambda: len(gcs.truth) > 10, 30)
        gcs.wait("the EKF's position from the feed", lambda: gcs.ekf_flags & EKF_POS_HORIZ_REL
                 and not gcs.ekf_flags & EKF_CONST_POS_MODE and gcs.local is not None, 120)
        gcs.pump(5.0)
        gcs.command(MAV_CMD_DO_SET_MODE, 1, GUIDED)
        gcs.pump(1.0)
        gcs.command(MAV_CMD_ARM, 1)
        gcs.pump(2.0)
        gcs.command(MAV_CMD_TAKEOFF, 0, 0, 0, 0, 0, 0, args.alt_m)
        gcs.wait("take-off", lambda: -gcs.here()[2] > 0.9 * args.alt_m, 60)
        gcs.pump(10.0)  # settle
        ref = gcs.here()
        drift_max, drift_end = track(gcs, args.hold_s, ref)
        result["hold"] = {"seconds": args.hold_s, "drift_max_m": drift_max,
                          "drift_end_m": drift_end, "bar_m": 0.15}
        print(f"hold {args.hold_s:.0f} s: true drift max {drift_max:.3f} m, "
              f"end {drift_end:.3f} m (bar 0.15)", flush=True)
        start, local = gcs.here(), gcs.local
        assert local is not None
        target = (start[0] + args.move_m, start[1])
        gcs.conn.mav.set_position_target_local_ned_send(
            0, args.target_system, 1, 1, POSITION_ONLY, local[0] + args.move_m, local[1],
            local[2], 0, 0, 0, 0, 0, 0, 0, 0)
        gcs.pump(15.0)
        move_err = horizontal(gcs.here(), target)
        result["move"] = {"m": args.move_m, "error_m": move_err, "bar_m": 0.1}
        print(f"move {args.move_m:.1f} m north: ends {move_err:.3f} m from its target "
              f"by truth (bar 0.1)", flush=True)
        gcs.pump(5.0)
        before = gcs.here()
        svc.send_signal(signal.SIGTERM)
        svc.wait(30)
        svc = start_nislam(args.nislam, args.out / "nislam.log")
        moved_max, moved_end = track(gcs, 30.0, before)
        result["restart"] = {"moved_max_m": moved_max, "moved_end_m": moved_end, "bar_m": 0.2}
        print(f"restart during the hover: moved max {moved_max:.3f} m, end {moved_end:.3f} m "
              f"(bar 0.2)", flush=True)
        gcs.command(MAV_CMD_DO_SET_MODE, 1, LAND)
        gcs.pump(10.0)
    finally:
        if svc.poll() is None:
            svc.send_signal(signal.SIGTERM)
            svc.wait(30)
        result["statustexts"] = gcs.texts
        (args.out / "sitl_acceptance.json").write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
