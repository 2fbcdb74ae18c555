#!/usr/bin/env python3
"""The fleet's cost at 1, 3, 10 vehicles (not a test): run it, read the figures.

1. Records a flight's results once: NI-SLAM on a synthetic orbit (`--scenario`,
   `--flight-s`, 640x480, 30 Hz), every TrackResult with its finished key
   frames, cached in results/fleet_scale/recorded.pkl.
2. For each fleet size N: a `nislam router` process, a `nislam ground`
   process, and N simulated vehicles in this process: each a ZenohOutput
   (the real publisher, a client of the router) fed the recorded results at
   30 Hz, looping, the vehicles a few frames apart. After --warmup-s it
   measures over --seconds: the router's and the ground's CPU (/proc, user +
   system), the payload bytes each vehicle put (pose, status, map), what the
   ground received (its fleet status queryable), and at the end whether the
   ground holds every key frame of every vehicle.

    .venv/bin/python scripts/fleet_scale.py [--sizes 1,3,10] [--seconds 30] [--secure] [--json]

--secure: mutual TLS on every link and the router's ACL (one certificate per
vehicle, made with openssl as docs/fleet.md shows).

The machine is shared: CPU figures read high when others run (say so when
quoting them). Bytes are payload bytes (zenoh adds ~10-30 bytes a message).
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import resource
import socket
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))  # the process helpers live with the tests

from fleet_pki import make_ca, make_cert  # noqa: E402
from subproc import JsonLinesProcess, free_port  # noqa: E402

from onboard.outputs.settings import ZenohConfig  # noqa: E402
from onboard.outputs.zenoh_out import ZenohOutput  # noqa: E402
from onboard.outputs.zenoh_session import open_session, session_config  # noqa: E402

NISLAM = REPO / ".venv" / "bin" / "nislam"
OUT = REPO / "results" / "fleet_scale"
RATE_HZ = 30.0
TICK_S = os.sysconf("SC_CLK_TCK")


def record(scenario: str, flight_s: float) -> list[Any]:
    """Every TrackResult of NI-SLAM on a synthetic flight (cached)."""
    cache = OUT / f"recorded_{scenario}_{flight_s:g}.pkl"
    if cache.exists():
        return pickle.loads(cache.read_bytes())
    from onboard.app.config import Config
    from onboard.fusion.registry import make_tracker
    from sim_replay.attitude import AttitudeErrorModel, attitude_for_replay
    from sim_replay.sim import SimOptions, simulate
    from sim_replay.tum import open_sequence

    flight = OUT / f"flight_{scenario}_{flight_s:g}"
    if not (flight / "rgb.txt").exists():
        simulate(scenario, flight, SimOptions(seconds=flight_s), progress=True)
    seq = open_sequence(flight, 0.02, True)
    attitude, _ = attitude_for_replay(seq, AttitudeErrorModel(), 0.2)
    tracker = make_tracker("nislam", seq.intrinsics, Config())
    results = [tracker.track(frame, attitude) for frame in seq.frames()]
    OUT.mkdir(parents=True, exist_ok=True)
    cache.write_bytes(pickle.dumps(results))
    return results


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK_S  # utime, stime


def own_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def fleet_status(session: Any) -> dict[str, Any]:
    for reply in session.get("nislam/@fleet/status", timeout=10.0):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())["vehicles"]
    return {}


def wait_text(proc: JsonLinesProcess, needle: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not any(needle in line for line in proc.text):
        if proc.proc.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"{proc.argv}: no {needle!r}: {proc.stderr[-2000:]}")
        time.sleep(0.05)


def tls_of(pki: Path | None, cn: str) -> dict[str, str]:
    """[zenoh] / [router] TLS keys for `cn` (made on first use), or none."""
    if pki is None:
        return {}
    if not (pki / f"{cn}.pem").exists():
        make_cert(pki, cn, "ca")
    return {"tls_root_ca": str(pki / "ca.pem"), "tls_certificate": str(pki / f"{cn}.pem"),
            "tls_private_key": str(pki / f"{cn}.key")}


def toml_of(section: str, values: dict[str, Any]) -> str:
    return f"[{section}]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in values.items())


def run_size(n: int, results: list[Any], warmup_s: float, seconds: float,
             pki: Path | None) -> dict[str, Any]:
    port = free_port(socket.SOCK_STREAM)
    ep = f"{'tls' if pki else 'tcp'}/127.0.0.1:{port}"
    ids = [f"sim{i:03d}" for i in range(n)]
    rcfg = OUT / f"router_{n}.toml"
    rcfg.write_text(toml_of("router", {"listen": [ep], **tls_of(pki, "router"),
                                       "acl": pki is not None, "vehicles": ids}))
    gcfg = OUT / f"ground_{n}.toml"
    gcfg.write_text(toml_of("zenoh", tls_of(pki, "ground")))
    router = JsonLinesProcess([str(NISLAM), "router", "--config", str(rcfg)])
    wait_text(router, "listening on")
    ground = JsonLinesProcess([str(NISLAM), "ground", "--connect", ep, "--out",
                               str(OUT / f"ground_{n}"), "--table-period", "0",
                               "--config", str(gcfg)])
    tool = open_session(session_config(ZenohConfig(connect=(ep,), **tls_of(pki, "ground")),
                                       mode="client", listen=()))
    vehicles = [ZenohOutput(ZenohConfig(vehicle=vid, mode="client", connect=(ep,),
                                        **tls_of(pki, vid))) for vid in ids]
    try:
        for v in vehicles:
            v.wait_connected(30.0)
        total = warmup_s + seconds
        t0 = time.monotonic()
        k = 0
        marks: dict[str, Any] = {}
        while True:
            now = time.monotonic()
            if not marks and now - t0 >= warmup_s:
                marks = {"t": now, "router": cpu_s(router.proc.pid),
                         "ground": cpu_s(ground.proc.pid), "self": own_cpu_s(),
                         "put": [v.stats()["bytes_put"] for v in vehicles],
                         "got": fleet_status(tool)}
            if now - t0 >= total:
                break
            for i, v in enumerate(vehicles):
                v.publish(results[(k + 7 * i) % len(results)])
            k += 1
            time.sleep(max(0.0, t0 + k / RATE_HZ - time.monotonic()))
        span = time.monotonic() - marks["t"]
        router_cpu = cpu_s(router.proc.pid) - marks["router"]
        ground_cpu = cpu_s(ground.proc.pid) - marks["ground"]
        self_cpu = own_cpu_s() - marks["self"]
        put = [v.stats()["bytes_put"] for v in vehicles]
        got = fleet_status(tool)
    finally:
        for v in vehicles:
            v.close()
    # The ground ends with every key frame? (what the vehicles held at close)
    wanted = {f"sim{i:03d}": v.run_stats()["keyframe_crc32"] for i, v in enumerate(vehicles)}
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        got_end = fleet_status(tool)
        complete = all(got_end.get(vid, {}).get("keyframe_crc32") == crcs
                       for vid, crcs in wanted.items())
        if complete:
            break
        time.sleep(0.5)
    tool.close()
    ground.stop()
    router.stop()
    kinds = ("pose", "status", "map")
    per_vehicle_put = {k: sum(put[i][k] - marks["put"][i][k] for i in range(n)) / n / span
                       for k in kinds}
    before = marks["got"]
    got_rate = {k: sum(got[vid]["bytes"][k] - before.get(vid, {"bytes": {k: 0}})["bytes"][k]
                       for vid in got) / n / span for k in kinds}
    return {
        "vehicles": n, "seconds": span,
        "router_cpu_pct": 100.0 * router_cpu / span,
        "ground_cpu_pct": 100.0 * ground_cpu / span,
        "vehicles_process_cpu_pct": 100.0 * self_cpu / span,
        "put_bytes_per_s_per_vehicle": per_vehicle_put,
        "ground_received_bytes_per_s_per_vehicle": got_rate,
        "router_in_kB_s": sum(per_vehicle_put.values()) * n / 1e3,
        "ground_has_every_keyframe": complete,
        "dropped_poses": sum(v.stats()["dropped_poses"] for v in vehicles),
        "ground_poses_per_s_per_vehicle": sum(
            got[vid]["poses"] - before.get(vid, {"poses": 0})["poses"] for vid in got) / n / span,
    }


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="1,3,10")
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--warmup-s", type=float, default=5.0)
    ap.add_argument("--scenario", default="circle")
    ap.add_argument("--flight-s", type=float, default=20.0)
    ap.add_argument("--secure", action="store_true",
                    help="mutual TLS and the ACL (certificates made with openssl)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    pki = None
    if args.secure:
        pki = OUT / "pki"
        if not (pki / "ca.pem").exists():
            make_ca(pki, "ca")
    results = record(args.scenario, args.flight_s)
    kf = sum(len(r.finished_keyframes) for r in results)
    print(f"recorded {len(results)} results, {kf} key-frame publications "
          f"({args.scenario}, {args.flight_s:g} s)", file=sys.stderr)
    rows = []
    for n in (int(s) for s in args.sizes.split(",")):
        row = run_size(n, results, args.warmup_s, args.seconds, pki)
        row["secure"] = args.secure
        rows.append(row)
        if args.json:
            print(json.dumps(row), flush=True)
        else:
            p, g = row["put_bytes_per_s_per_vehicle"], row["ground_received_bytes_per_s_per_vehicle"]
            print(f"{'TLS+ACL ' if args.secure else ''}N={n:3d}  router CPU {row['router_cpu_pct']:5.1f} %  ground CPU "
                  f"{row['ground_cpu_pct']:5.1f} %  vehicles' process {row['vehicles_process_cpu_pct']:5.1f} %  "
                  f"per vehicle put: pose {p['pose']:.0f} B/s, status {p['status']:.0f} B/s, "
                  f"map {p['map'] / 1e3:.1f} kB/s; ground got pose {g['pose']:.0f} B/s, "
                  f"map {g['map'] / 1e3:.1f} kB/s; router in {row['router_in_kB_s']:.0f} kB/s; "
                  f"({row['ground_poses_per_s_per_vehicle']:.1f} poses/s); complete "
                  f"{row['ground_has_every_keyframe']}, dropped {row['dropped_poses']}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
