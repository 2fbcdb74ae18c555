"""A MAVLink 2 peer that signs (or not) what it sends, in its own process.

    python tests/peers/mavlink_signed_peer.py PORT [--key HEX]

Listens on udpin:127.0.0.1:PORT as system 1, component 1. With --key it
signs its messages with that 32-byte key and refuses unsigned or wrongly
signed ones; without, it sends unsigned. Once it has heard any bytes it sends
a TIMESYNC request (tc1 = 0) every 50 ms. stdout, one JSON line each:
{"ready": true}; every message accepted from component 197 as {"t", "type",
"signed", "tc1"?}; every message refused as {"refused": reason}. SIGTERM ends it.
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
    ap.add_argument("port", type=int)
    ap.add_argument("--key", help="signing key, 64 hex digits")
    args = ap.parse_args()
    os.environ["MAVLINK20"] = "1"  # an entry point: before pymavlink's first import
    from pymavlink import mavutil

    stop: list[int] = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{args.port}", source_system=1,
                                      source_component=1)
    if args.key:
        conn.setup_signing(bytes.fromhex(args.key), sign_outgoing=True,
                           allow_unsigned_callback=None, link_id=1)
    print(json.dumps({"ready": True}), flush=True)
    next_ts = 0.0
    while not stop:
        conn.select(0.02)
        while (msg := conn.recv_msg()) is not None:
            kind = msg.get_type()
            if kind == "BAD_DATA":
                if "signature" in str(getattr(msg, "reason", "")):
                    print(json.dumps({"refused": str(msg.reason)}), flush=True)
                continue
            if msg.get_srcComponent() == 197:
                line = {"t": time.monotonic(), "type": kind, "signed": msg.get_signed()}
                if kind == "TIMESYNC":
                    line["tc1"] = msg.tc1
                print(json.dumps(line), flush=True)
        now = time.monotonic()
        if conn.clients and now >= next_ts:  # udpin: the addresses heard from
            conn.mav.timesync_send(0, time.monotonic_ns())
            next_ts = now + 0.05
    conn.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
