"""A MAVLink peer in its own process, for the tests and scripts/bench_outputs.py.

    python tests/mavlink_peer.py udpin:127.0.0.1:PORT [--timesync-s X] [--duration-s X]

Prints `{"ready": true}` once the link is open, then every message received
as one JSON line on stdout: {"t": monotonic receive time [s], "mavpackettype": ...,
"src_system": ..., "src_component": ..., <the message's fields>}. With
--timesync-s it plays an autopilot asking for TIMESYNC (tc1 = 0) at that
period once it has heard from someone. Stops on SIGTERM, SIGINT, or after
--duration-s.
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
    args = ap.parse_args()
    os.environ["MAVLINK20"] = "1"  # before pymavlink's first import (an entry point)
    from pymavlink import mavutil

    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    conn = mavutil.mavlink_connection(args.connect, source_system=1, source_component=1)
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
            heard = True
            line = {"t": time.monotonic(), "mavpackettype": msg.get_type(),
                    "src_system": msg.get_srcSystem(), "src_component": msg.get_srcComponent()}
            line.update(msg.to_dict())
            if isinstance(line.get("text"), bytes):
                line["text"] = line["text"].decode("ascii", "replace")
            print(json.dumps(line), flush=True)
        now = time.monotonic()
        if args.timesync_s > 0 and heard and now >= next_ts:
            conn.mav.timesync_send(0, time.monotonic_ns())
            next_ts = now + args.timesync_s
    conn.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
