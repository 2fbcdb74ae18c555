"""A simulated vehicle in its own process, for the closed-loop tests: it
plays ArduPilot SITL's side of `nislam run --sim-follow`.

    python tests/peers/vehicle_sim.py udpin:127.0.0.1:PORT --flight circle --seconds 4

Waits for MAV_CMD_SET_MESSAGE_INTERVAL asking for SIM_STATE (108), acks it,
then streams SIM_STATE at the requested rate as SITL fills it (quaternion
and body rates, NED velocity, lat/lon as degE7 both in the float fields and
in lat_int/lon_int, alt in m), flying the named flight of
sim_replay.flights (or `guided`: landed, a take-off to 1 m, a 2 m move north):
hovering at its start pose until the first ODOMETRY
arrives and `--hover-s` longer (a pilot takes off once the feed is there),
then `--seconds` of the flight, then hovering at its end. Its NED position is the flight's position
minus the flight's start (so its first state is the flight's start pose
seen from the EKF origin), about ArduPilot's CMAC home.

SET_GPS_GLOBAL_ORIGIN is answered with GPS_GLOBAL_ORIGIN, as ArduPilot does.

stdout, one JSON object a line: {"ready": true}; {"flight_start": T} (the
monotonic time [s] of the flight's t = 0); every ODOMETRY, HEARTBEAT,
STATUSTEXT and SET_GPS_GLOBAL_ORIGIN received as {"t": receive time, "mavpackettype": ..., fields};
{"done": true} after the flight. Stops on SIGTERM/SIGINT.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

HOME_LAT_E7, HOME_LON_E7, HOME_ALT_M = -353632621, 1491652374, 584.0  # ArduPilot CMAC
M_PER_DEG_E7 = 0.011131884502145034  # ArduPilot's LOCATION_SCALING_FACTOR
REPORT = ("ODOMETRY", "HEARTBEAT", "STATUSTEXT", "SET_GPS_GLOBAL_ORIGIN")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("connect")
    ap.add_argument("--flight", default="circle")
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--hover-s", type=float, default=1.5)
    ap.add_argument("--after-s", type=float, default=600.0, help="hover this long after it")
    args = ap.parse_args()
    os.environ["MAVLINK20"] = "1"  # before pymavlink's first import
    import numpy as np
    from pymavlink import mavutil
    from scipy.spatial.transform import Rotation

    from sim_replay.flights import Flight, Scenario, scenario

    def _smooth(x: np.ndarray) -> np.ndarray:
        x = np.clip(x, 0.0, 1.0)
        return x**3 * (10.0 - 15.0 * x + 6.0 * x * x)  # C2: no step in the tilt

    def _guided(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """SITL's acceptance flight in small: landed 2 s, take off to 1 m in
        2 s, hover 2 s, 2 m north in 4 s, hover; nose north."""
        x = 2.0 * _smooth((t - 6.0) / 4.0)
        z = -1.0 * _smooth((t - 2.0) / 2.0)
        return np.stack([x, np.zeros_like(x), z], axis=1), np.zeros_like(x)

    scen = (Scenario("guided", "room", "take-off, hover, 2 m north", _guided)
            if args.flight == "guided" else scenario(args.flight))
    flight = Flight(scen)
    p0 = flight.position([0.0])[0]

    def state(t_s: float) -> tuple:
        # Beyond the flight: hover where it ended (a pose, no motion).
        tf = min(t_s, args.seconds)
        p, R = flight.body_pose([tf])
        h = 1e-3
        if t_s < args.seconds:
            v = flight.velocity([tf])[0]
            R1 = flight.body_pose([tf + h])[1][0]
            w = Rotation.from_matrix(R[0].T @ R1).as_rotvec() / h
        else:
            v, w = np.zeros(3), np.zeros(3)
        return p[0] - p0, R[0], v, w

    stop: list[int] = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    conn = mavutil.mavlink_connection(args.connect, source_system=1, source_component=1)
    print(json.dumps({"ready": True}), flush=True)
    interval_s: float | None = None
    t_start: float | None = None
    t_next = 0.0
    done = False
    lon_scale = math.cos(math.radians(HOME_LAT_E7 * 1e-7))
    while not stop:
        # Sleep until the next state is due (or a message arrives): a busy
        # peer would take the CPU the service under test needs.
        wait_s = 0.02 if interval_s is None else min(0.02, max(0.0, t_next - time.monotonic()))
        conn.select(wait_s)
        while (msg := conn.recv_msg()) is not None:
            kind = msg.get_type()
            if kind == "COMMAND_LONG" and msg.command == 511 and int(msg.param1) == 108:
                conn.mav.command_ack_send(511, 0)
                if interval_s is None:
                    t_next = time.monotonic()
                interval_s = msg.param2 * 1e-6
            elif kind in REPORT:
                if kind == "SET_GPS_GLOBAL_ORIGIN":  # as ArduPilot: confirm it
                    conn.mav.gps_global_origin_send(msg.latitude, msg.longitude, msg.altitude,
                                                    msg.time_usec)
                if kind == "ODOMETRY" and t_start is None:
                    t_start = time.monotonic() + args.hover_s
                    print(json.dumps({"flight_start": t_start}), flush=True)
                line = {"t": time.monotonic(), "mavpackettype": kind,
                        "src_system": msg.get_srcSystem(), "src_component": msg.get_srcComponent()}
                line.update(msg.to_dict())
                if isinstance(line.get("text"), bytes):
                    line["text"] = line["text"].decode("ascii", "replace")
                print(json.dumps(line), flush=True)
        now = time.monotonic()
        if interval_s is None or now < t_next:
            continue
        t_next = max(t_next + interval_s, now - interval_s)
        p, R, v, w = state(-1.0 if t_start is None else now - t_start)
        lat = HOME_LAT_E7 + p[0] / M_PER_DEG_E7
        lon = HOME_LON_E7 + p[1] / (M_PER_DEG_E7 * lon_scale)
        x, y, z, qw = Rotation.from_matrix(R).as_quat()
        roll, pitch, yaw = Rotation.from_matrix(R).as_euler("ZYX")[::-1]
        conn.mav.sim_state_send(qw, x, y, z, roll, pitch, yaw, 0.0, 0.0, -9.81,
                                w[0], w[1], w[2], lat, lon, HOME_ALT_M - p[2], 0.0, 0.0,
                                v[0], v[1], v[2], int(round(lat)), int(round(lon)))
        if t_start is None:
            continue
        if not done and now - t_start >= args.seconds:
            done = True
            print(json.dumps({"done": True}), flush=True)
        if now - t_start >= args.seconds + args.after_s:
            break
    conn.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
