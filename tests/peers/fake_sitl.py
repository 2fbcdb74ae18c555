"""A stand-in for ArduPilot SITL's MAVLink side, to try scripts/sitl_acceptance.py
without SITL (its plumbing: modes, arming, take-off, position targets,
truth, a service restart), never its flight control.

    python tests/peers/fake_sitl.py --companion udpin:127.0.0.1:P1 --gcs udpin:127.0.0.1:P2

Two links, as SITL's two ports: the companion's (nislam --sim-follow) and the
ground station's. On either it answers MAV_CMD_SET_MESSAGE_INTERVAL for
SIM_STATE (108), LOCAL_POSITION_NED (32) and EKF_STATUS_REPORT (193) and
streams them; HEARTBEAT at 1 Hz (a quadrotor, ArduPilot). The vehicle starts
landed at CMAC heading north; DO_SET_MODE, arming and NAV_TAKEOFF are
acknowledged, and in GUIDED it moves to the take-off height or a
SET_POSITION_TARGET_LOCAL_NED target at up to 0.5 m/s, level, nose north.
The EKF reports a relative position (flags 8) once ODOMETRY arrives, and
LOCAL_POSITION_NED is the truth (a perfect EKF). Stops on SIGTERM.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time

HOME_LAT_E7, HOME_LON_E7, HOME_ALT_M = -353632621, 1491652374, 584.0
M_PER_DEG_E7 = 0.011131884502145034
SPEED_M_S = 0.5


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--companion", required=True)
    ap.add_argument("--gcs", required=True)
    args = ap.parse_args()
    os.environ["MAVLINK20"] = "1"
    import math

    import numpy as np
    from pymavlink import mavutil

    stop: list[int] = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    links = [mavutil.mavlink_connection(u, source_system=1, source_component=1)
             for u in (args.companion, args.gcs)]
    rates: list[dict[int, float]] = [{}, {}]  # per link: message id -> interval [s]
    due: list[dict[int, float]] = [{}, {}]
    p = np.zeros(3)
    target: np.ndarray | None = None
    mode, armed, ekf_ok = 0, False, False
    t_last = time.monotonic()
    next_beat = 0.0
    lon_scale = math.cos(math.radians(HOME_LAT_E7 * 1e-7))
    print("ready", flush=True)
    while not stop:
        for k, conn in enumerate(links):
            while (msg := conn.recv_msg()) is not None:
                kind = msg.get_type()
                if kind == "ODOMETRY":
                    ekf_ok = True
                elif kind == "COMMAND_LONG":
                    cmd = msg.command
                    if cmd == 511:
                        rates[k][int(msg.param1)] = msg.param2 * 1e-6
                    elif cmd == 176:
                        mode = int(msg.param2)
                    elif cmd == 400:
                        armed = msg.param1 == 1
                    elif cmd == 22 and armed and mode == 4:
                        target = np.array([p[0], p[1], -msg.param7])
                    conn.mav.command_ack_send(cmd, 0)
                elif kind == "SET_POSITION_TARGET_LOCAL_NED" and armed and mode == 4:
                    target = np.array([msg.x, msg.y, msg.z])
                elif kind == "SET_GPS_GLOBAL_ORIGIN":
                    conn.mav.gps_global_origin_send(msg.latitude, msg.longitude, msg.altitude,
                                                    msg.time_usec)
        now = time.monotonic()
        dt, t_last = now - t_last, now
        v = np.zeros(3)
        if mode == 9:  # LAND
            target = np.array([p[0], p[1], 0.0])
        if target is not None:
            step = target - p
            dist = float(np.linalg.norm(step))
            if dist > 1e-6:
                v = step / dist * min(SPEED_M_S, dist / max(dt, 1e-3))
                p = p + v * dt
        if now >= next_beat:
            next_beat = now + 1.0
            for conn in links:
                conn.mav.heartbeat_send(2, 3, 128 * armed + 1, mode, 4)
        for k, conn in enumerate(links):
            for msg_id, interval in rates[k].items():
                if now < due[k].get(msg_id, 0.0):
                    continue
                due[k][msg_id] = now + interval
                if msg_id == 108:
                    lat = HOME_LAT_E7 + p[0] / M_PER_DEG_E7
                    lon = HOME_LON_E7 + p[1] / (M_PER_DEG_E7 * lon_scale)
                    conn.mav.sim_state_send(1, 0, 0, 0, 0, 0, 0, 0, 0, -9.81, 0, 0, 0,
                                            lat, lon, HOME_ALT_M - p[2], 0, 0, *v,
                                            int(round(lat)), int(round(lon)))
                elif msg_id == 32:
                    conn.mav.local_position_ned_send(int(now * 1e3) % 2**32, *p, *v)
                elif msg_id == 193:
                    conn.mav.ekf_status_report_send(8 if ekf_ok else 0, 0, 0, 0, 0, 0)
        time.sleep(0.002)
    return 0


if __name__ == "__main__":
    sys.exit(main())
