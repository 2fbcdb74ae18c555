"""A pymavlink autopilot stand-in, run as its own process on 127.0.0.1.

    python tests/peers/mavlink_autopilot.py --port PORT [--boot-age-s S]

Listens on udpin:127.0.0.1:PORT as system 1, component 1 (autopilot). It
answers COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL (511) with COMMAND_ACK
and, once asked for ATTITUDE_QUATERNION (param1 = 31), streams it at the
requested interval (param2, us). time_boot_ms counts from a boot instant
`--boot-age-s` before start; the attitude is a yaw about the NED z axis of
YAW_RATE * boot seconds (q1..q4 = w, x, y, z) so a test can check every
sample. Sends a 1 Hz HEARTBEAT once it knows its peer.

stdout: "ready boot_origin_ns=N" (our monotonic clock at time_boot_ms = 0,
the same CLOCK_MONOTONIC every process on the host shares), then
"interval_us=N" per accepted request. stdin: "quit" (or EOF) ends it.
"""

from __future__ import annotations

import argparse
import math
import os
import select
import sys
import time

YAW_RATE_RAD_S = 0.5


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--boot-age-s", type=float, default=100.0)
    args = ap.parse_args()

    os.environ["MAVLINK20"] = "1"  # a script's entry point: set before importing pymavlink
    from pymavlink import mavutil

    mav_link = mavutil.mavlink
    conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{args.port}", source_system=1,
                                      source_component=1)
    boot_origin_ns = time.monotonic_ns() - int(args.boot_age_s * 1e9)
    print(f"ready boot_origin_ns={boot_origin_ns}", flush=True)

    interval_s: float | None = None
    next_att = next_hb = time.monotonic()
    while True:
        now = time.monotonic()
        if interval_s is not None and now >= next_att:
            boot_ns = time.monotonic_ns() - boot_origin_ns
            yaw = YAW_RATE_RAD_S * boot_ns * 1e-9
            conn.mav.attitude_quaternion_send(
                boot_ns // 1_000_000, math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2),
                0.0, 0.0, YAW_RATE_RAD_S)
            next_att = max(next_att + interval_s, now - interval_s)
        if conn.clients and now >= next_hb:
            conn.mav.heartbeat_send(mav_link.MAV_TYPE_QUADROTOR,
                                    mav_link.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0,
                                    mav_link.MAV_STATE_ACTIVE)
            next_hb = now + 1.0
        wait = max(0.0, min(next_att if interval_s else now + 0.05, next_hb) - time.monotonic())
        r, _w, _x = select.select([conn.fd, sys.stdin.fileno()], [], [], min(wait, 0.05))
        if sys.stdin.fileno() in r:
            line = sys.stdin.readline()
            if not line or line.strip() == "quit":
                break
        while True:
            msg = conn.recv_match(blocking=False)
            if msg is None:
                break
            if msg.get_type() == "COMMAND_LONG" and msg.command == 511:
                ok = int(msg.param1) == 31 and msg.param2 > 0
                conn.mav.command_ack_send(511, 0 if ok else 4)  # ACCEPTED / FAILED
                if ok:
                    interval_s = msg.param2 * 1e-6
                    next_att = time.monotonic()
                    print(f"interval_us={int(msg.param2)}", flush=True)
    conn.close()


if __name__ == "__main__":
    main()
