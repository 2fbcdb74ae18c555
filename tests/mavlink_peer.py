"""A MAVLink peer in its own process, for the tests and scripts/bench_outputs.py.

    python tests/mavlink_peer.py udpin:127.0.0.1:PORT [--timesync-s X] [--duration-s X]
                                 [--clock-shift-s X]

Prints `{"ready": true}` once the link is open, then every message received
as one JSON line on stdout: {"t": monotonic receive time [s], "mavpackettype": ...,
"src_system": ..., "src_component": ..., <the message's fields>}. With
--timesync-s it plays an autopilot asking for TIMESYNC (tc1 = 0) at that
period once it has heard from someone. It answers TIMESYNC requests (tc1 = 0),
as ArduPilot and PX4 do, with its own clock: time.monotonic_ns() shifted by
--clock-shift-s (an autopilot's clock, which started at another time); its
own requests are stamped with that clock too ("t" stays the host's
monotonic time). Stops on SIGTERM, SIGINT, or after --duration-s.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("connect")
    ap.add_argument("--timesync-s", type=float, default=0.0)
    ap.add_argument("--duration-s", type=float, default=600.0)
    ap.add_argument("--clock-shift-s", type=float, default=0.0)
    args = ap.parse_args()
    os.environ["MAVLINK20"] = "1"  # before pymavlink's first import (an entry point)
    from pymavlink import mavutil

    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    conn = mavutil.mavlink_connection(args.connect, source_system=1, source_component=1)
    shift_ns = round(args.clock_shift_s * 1e9)

    def clock_ns() -> int:  # the autopilot's clock
        return time.monotonic_ns() + shift_ns

    print(json.dumps({"ready": True}), flush=True)
    end = time.monotonic() + args.duration_s
    next_ts = 0.0
    heard = False
    while not stop and time.monotonic() < end:
        conn.select(0.02)
        while True:
            msg = conn.recv_msg()
            if msg is None:
                break
            if msg.get_type() == "BAD_DATA":
                continue
            if msg.get_type() == "TIMESYNC" and msg.tc1 == 0:  # answer at once
                conn.mav.timesync_send(clock_ns(), msg.ts1)
            heard = True
            line = {"t": time.monotonic(), "mavpackettype": msg.get_type(),
                    "src_system": msg.get_srcSystem(), "src_component": msg.get_srcComponent()}
            line.update(msg.to_dict())
            if isinstance(line.get("text"), bytes):
                line["text"] = line["text"].decode("ascii", "replace")
            print(json.dumps(line), flush=True)
        now = time.monotonic()
        if args.timesync_s > 0 and heard and now >= next_ts:
            conn.mav.timesync_send(0, clock_ns())
            next_ts = now + args.timesync_s
    conn.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
