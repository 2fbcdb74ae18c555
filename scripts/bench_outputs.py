#!/usr/bin/env python3
"""Benchmark of the outputs (not a test): run it, read the figures.

1. MAVLink at the camera rate: synthetic results published at --rate-hz for
   --seconds into a MavlinkOutput; a pymavlink peer in another process
   (tests/mavlink_peer.py) stamps every ODOMETRY on arrival. Reports the
   achieved rate, the inter-arrival jitter and the capture-to-peer latency.
2. Per-frame cost inside the tracking loop: the real tracker on the first
   --frames frames of a sequence (decoded into memory first), paced at
   --rate-hz, with (a) no output, (b) MAVLink + zenoh with their peers
   running in other processes (tests/mavlink_peer.py, `nislam listen`),
   (c) MAVLink + zenoh with no peer reachable. Reports the time spent in
   `publish()` (wall clock, and the loop thread's CPU time: the difference
   is waiting, for the GIL or for a core) and in `track()` (to show what the
   output threads cost the loop), and what the peers received.

    .venv/bin/python scripts/bench_outputs.py [SEQ_DIR] [--frames N] [--seconds S]
                                              [--switch-interval-ms X] [--json]
"""

from __future__ import annotations

import argparse
import json
import signal
import socket
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))  # the peer helpers live with the tests

from fake_results import track_result  # noqa: E402
from subproc import JsonLinesProcess, free_port, python_script  # noqa: E402

from onboard.app.bench import pin_one_core, replay_attitude
from onboard.app.config import Config, with_tracker_resolved
from onboard.fusion.registry import make_tracker
from onboard.outputs.group import NullOutput, Output, OutputGroup
from onboard.outputs.mapcodec import encode_keyframe
from onboard.outputs.mavlink import MavlinkOutput
from onboard.outputs.settings import MavlinkConfig, ZenohConfig
from onboard.outputs.zenoh_out import ZenohOutput
from sim_replay.tum import open_sequence

PEER = REPO / "tests" / "mavlink_peer.py"
NISLAM = REPO / ".venv" / "bin" / "nislam"


def pct(values: list[float] | np.ndarray, scale: float = 1.0) -> dict[str, float | None]:
    v = np.asarray(values, dtype=np.float64) * scale
    if len(v) == 0:
        return {"median": None, "p95": None, "p99": None, "max": None}
    return {"median": float(np.median(v)), "p95": float(np.percentile(v, 95)),
            "p99": float(np.percentile(v, 99)), "max": float(v.max())}


def start_mavlink_peer(port: int) -> JsonLinesProcess:
    peer = JsonLinesProcess(python_script(PEER, f"udpin:127.0.0.1:{port}"))
    peer.wait_for(lambda lines: any(m.get("ready") for m in lines), 60, "mavlink peer")
    return peer


def pace(t0: float, i: int, rate_hz: float) -> None:
    time.sleep(max(0.0, t0 + i / rate_hz - time.monotonic()))


# --------------------------------------------------------------------------- 1


def mavlink_rate(seconds: float, rate_hz: float) -> dict[str, Any]:
    port = free_port()
    peer = start_mavlink_peer(port)
    out = MavlinkOutput(MavlinkConfig(connect=f"udpout:127.0.0.1:{port}"))
    n = int(seconds * rate_hz)
    publish_s = []
    try:
        t0 = time.monotonic()
        for i in range(n):
            pace(t0, i, rate_hz)
            r = track_result(time.monotonic(), [0.01 * i, 0.0, 0.0])  # "captured" now
            t = time.perf_counter()
            out.publish(r)
            publish_s.append(time.perf_counter() - t)
        peer.wait_for(lambda lines: sum(m.get("mavpackettype") == "ODOMETRY"
                                        for m in lines) >= n, 30, "all ODOMETRY")
    finally:
        out.close()
        peer.stop()
    odo = peer.of_type("ODOMETRY", key="mavpackettype")
    arrival = np.array([m["t"] for m in odo])
    gaps = np.diff(arrival)
    latency = arrival - np.array([m["time_usec"] for m in odo]) * 1e-6
    return {
        "sent": n, "received": len(odo),
        "rate_hz": (len(odo) - 1) / (arrival[-1] - arrival[0]),
        "interval_ms_mean": float(gaps.mean() * 1e3),
        "interval_ms_std": float(gaps.std() * 1e3),
        "interval_abs_dev_ms": pct(np.abs(gaps - 1.0 / rate_hz), 1e3),
        "latency_ms": pct(latency, 1e3),
        "publish_us": pct(publish_s, 1e6),
    }


# --------------------------------------------------------------------------- 2


def load_frames(seq_dir: Path, frames: int):
    cfg = with_tracker_resolved(Config(), service=True)  # the loop's tracker
    pin_one_core()
    seq = open_sequence(seq_dir, cfg.replay.assoc_max_dt_s, cfg.replay.undistort)
    attitude, _ = replay_attitude(seq, cfg)
    return cfg, seq, attitude, seq.load_all(frames)


def loop(cfg: Config, seq, attitude, frames, out: Output, rate_hz: float) -> dict[str, Any]:
    tracker = make_tracker(cfg.tracker.name, seq.intrinsics, cfg)
    track_s, publish_s, publish_cpu_s, keyframes = [], [], [], []
    t0 = time.monotonic()
    for i, frame in enumerate(frames):
        pace(t0, i, rate_hz)
        t = time.perf_counter()
        result = tracker.track(frame, attitude)
        t1 = time.perf_counter()
        c1 = time.thread_time()
        out.publish(result)
        c2 = time.thread_time()
        t2 = time.perf_counter()
        track_s.append(t1 - t)
        publish_s.append(t2 - t1)
        publish_cpu_s.append(c2 - c1)
        keyframes.extend(result.finished_keyframes)
    last = tracker.finish()
    if last is not None:
        out.publish_keyframe(last)
        keyframes.append(last)
    encode_s = []
    for kf in keyframes:
        t = time.perf_counter()
        encode_keyframe(kf)
        encode_s.append(time.perf_counter() - t)
    return {"frames": len(frames), "keyframes": len(keyframes), "track_ms": pct(track_s, 1e3),
            "publish_us": pct(publish_s, 1e6), "publish_cpu_us": pct(publish_cpu_s, 1e6),
            "keyframe_encode_ms": pct(encode_s, 1e3)}


def outputs_cost(seq_dir: Path, n_frames: int, rate_hz: float) -> dict[str, Any]:
    cfg, seq, attitude, frames = load_frames(seq_dir, n_frames)
    res: dict[str, Any] = {"sequence": str(seq_dir), "rate_hz": rate_hz}
    res["none"] = loop(cfg, seq, attitude, frames, NullOutput(), rate_hz)

    # (b) peers in other processes
    mport, zep = free_port(), f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    peer = start_mavlink_peer(mport)
    zout = ZenohOutput(ZenohConfig(vehicle="bench", listen=(zep,)))
    listener = JsonLinesProcess([str(NISLAM), "listen", "--connect", zep, "--vehicle", "bench",
                                 "--json"])
    listener.wait_for(lambda lines: any(m.get("type") == "map" for m in lines), 60, "listener")
    zout.wait_for_subscribers(30)
    group = OutputGroup([MavlinkOutput(MavlinkConfig(connect=f"udpout:127.0.0.1:{mport}")), zout])
    try:
        res["with_peers"] = loop(cfg, seq, attitude, frames, group, rate_hz)
        group.close()
        stats = {"mavlink": group.outputs[0].stats(), "zenoh": zout.stats()}
        res["with_peers"]["output_stats"] = stats
        sent, published = stats["mavlink"]["poses_sent"], stats["zenoh"]["poses_published"]
        for proc, pred in (
            (peer, lambda ls: sum(m.get("mavpackettype") == "ODOMETRY" for m in ls) >= sent),
            (listener, lambda ls: sum(m.get("type") == "pose" for m in ls) >= published),
        ):
            try:
                proc.wait_for(pred, 10, "everything sent arrived")
            except AssertionError as e:
                print(f"warning: {str(e)[:200]}", file=sys.stderr)
    finally:
        group.close()
        peer.stop()
        listener.stop(signal.SIGTERM)
    res["with_peers"]["received"] = {
        "mavlink_odometry": len(peer.of_type("ODOMETRY", key="mavpackettype")),
        "zenoh_poses": len(listener.of_type("pose")),
        "zenoh_keyframes": len(listener.of_type("keyframe")),
    }

    # (c) nobody listening
    group = OutputGroup([
        MavlinkOutput(MavlinkConfig(connect=f"udpout:127.0.0.1:{free_port()}")),
        ZenohOutput(ZenohConfig(vehicle="bench",
                                connect=(f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}",))),
    ])
    try:
        res["no_peer"] = loop(cfg, seq, attitude, frames, group, rate_hz)
        res["no_peer"]["output_stats"] = {"mavlink": group.outputs[0].stats(),
                                          "zenoh": group.outputs[1].stats()}
    finally:
        group.close()
    return res


# --------------------------------------------------------------------------- report


def fmt(d: dict[str, float | None], unit: str) -> str:
    return ", ".join(f"{k} {v:.3g} {unit}" for k, v in d.items() if v is not None)


def report(rate: dict[str, Any], cost: dict[str, Any]) -> None:
    print(f"MAVLink ODOMETRY at {cost['rate_hz']:g} Hz: {rate['received']}/{rate['sent']} "
          f"received, {rate['rate_hz']:.2f} Hz achieved")
    print(f"  interval {rate['interval_ms_mean']:.2f} ms mean, {rate['interval_ms_std']:.3f} ms "
          f"std; |interval - period|: {fmt(rate['interval_abs_dev_ms'], 'ms')}")
    print(f"  capture -> peer latency: {fmt(rate['latency_ms'], 'ms')}")
    print(f"  publish(): {fmt(rate['publish_us'], 'us')}")
    print(f"Loop on {cost['sequence']}, {cost['none']['frames']} frames at {cost['rate_hz']:g} Hz, "
          f"{cost['none']['keyframes']} key frames")
    for name in ("none", "with_peers", "no_peer"):
        c = cost[name]
        print(f"  {name:<10} publish() {fmt(c['publish_us'], 'us')}")
        print(f"  {'':<10} its CPU   {fmt(c['publish_cpu_us'], 'us')}")
        print(f"  {'':<10} track()   {fmt(c['track_ms'], 'ms')}")
    enc = fmt(cost["none"]["keyframe_encode_ms"], "ms")
    print(f"  key-frame encoding on the map thread: {enc}")
    print(f"  peers received: {cost['with_peers']['received']}")
    for name in ("with_peers", "no_peer"):
        st = cost[name]["output_stats"]
        print(f"  {name}: mavlink dropped {st['mavlink']['dropped']}, errors "
              f"{st['mavlink']['link_errors']}; zenoh dropped {st['zenoh']['dropped_poses']}, "
              f"errors {st['zenoh']['errors']}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("seq_dir", nargs="?", type=Path,
                    default=REPO.parent / "shared" / "data" / "tum_fr1_rpy")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rate-hz", type=float, default=30.0)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--switch-interval-ms", type=float, metavar="X",
                    help="sys.setswitchinterval for this run (CPython default 5 ms): how long "
                         "the loop may wait for the GIL while an output thread runs Python")
    args = ap.parse_args()
    if args.switch_interval_ms is not None:
        sys.setswitchinterval(args.switch_interval_ms * 1e-3)
    rate = mavlink_rate(args.seconds, args.rate_hz)
    cost = outputs_cost(args.seq_dir, args.frames, args.rate_hz)
    if args.json:
        print(json.dumps({"mavlink_rate": rate, "loop": cost}, indent=2))
    else:
        report(rate, cost)
    return 0


if __name__ == "__main__":
    sys.exit(main())
