"""Soak benchmark of the onboard service (a script, not a test).

    python scripts/soak.py [--minutes 10] [--flight DIR] [--out DIR]

Runs `nislam run --replay FLIGHT --loop` (the flight forwards and backwards
in turn) for the given time with the demo outputs (MAVLink to 127.0.0.1, zenoh
on a free 127.0.0.1 port, the zenoh map capped at 2 MB), samples the
process's resident memory (VmRSS) every 5 s, and reports RSS at start and end
(the last sample before the service's final summary) and its trend past
minute 1, and per minute: the frame rate, resets, dropped frames, the loop's
per-frame time (the service's own statistics periods: track + publish, on the
loop thread) and the pose latency from capture to written on the MAVLink link
(run.json `latency_minutes`, onboard/app/latency.py). The MAVLink peer is
tests/mavlink_peer.py playing the autopilot (it answers TIMESYNC), so the
capture-to-arrival latency and the delay advice come out too. Without
--flight it renders a 20 s `circle` flight (640x480) first. Writes
soak.json beside the service's metrics.json and run.json in --out.
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
NISLAM = REPO / ".venv" / "bin" / "nislam"


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def worst(periods: list[dict], key: str) -> float | None:
    """The largest value of `key` over statistics periods (None: no frames)."""
    vals = [p[key] for p in periods if p[key] is not None]
    return max(vals) if vals else None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--flight", type=Path, help="TUM-layout flight to loop (default: render one)")
    ap.add_argument("--out", type=Path, default=REPO / "results" / "soak")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    flight = args.flight
    if flight is None:
        flight = args.out / "flight"
        if not (flight / "rgb.txt").exists():
            subprocess.run([str(NISLAM), "sim", "circle", "--seconds", "20", "--out", str(flight),
                            "--quiet"], check=True)
    cfg = args.out / "soak.toml"
    mav_port = free_udp_port()
    peer = subprocess.Popen([sys.executable, str(REPO / "tests" / "mavlink_peer.py"),
                             f"udpin:127.0.0.1:{mav_port}", "--duration-s", f"{args.minutes * 60 + 120:g}"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    cfg.write_text(
        f"[mavlink]\nenabled = true\nconnect = \"udpout:127.0.0.1:{mav_port}\"\n"
        f"[zenoh]\nenabled = true\nlisten = [\"tcp/127.0.0.1:{free_tcp_port()}\"]\n"
        # The map held for late joiners grows by design up to map_max_mb
        # (512 MB by default). 2 MB is full within the first minute and then
        # evicts all along, so RSS past minute 1 shows the service itself,
        # eviction path included, not the map filling up.
        "map_max_mb = 2.0\n"
        "[service]\nstats_period_s = 10.0\n")
    seconds = args.minutes * 60.0
    proc = subprocess.Popen(
        [str(NISLAM), "run", "--replay", str(flight), "--loop", "--seconds", f"{seconds:g}",
         "--config", str(cfg), "--out", str(args.out / "run")],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    samples: list[tuple[float, float]] = []  # (seconds since start, RSS MB)
    lines: list[str] = []
    summary_at: list[float] = []  # when the final summary began: the loop is over

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            if line.startswith("source ") and not summary_at:
                summary_at.append(time.monotonic() - t0)
            lines.append(line.rstrip())
            print(line.rstrip(), flush=True)

    t0 = time.monotonic()
    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    while proc.poll() is None:
        rss = rss_mb(proc.pid)
        if rss is not None:
            samples.append((time.monotonic() - t0, rss))
        time.sleep(5.0)
    reader.join(10)
    peer.terminate()
    peer.wait(10)
    if proc.returncode != 0:
        print(f"service exited with {proc.returncode}", file=sys.stderr)
        return 1
    # Only samples of the running loop: at shutdown the process frees its
    # holdings, and a sample then would hide growth.
    if summary_at:
        samples = [(t, r) for t, r in samples if t < summary_at[0]]
    metrics = json.loads((args.out / "run" / "metrics.json").read_text())
    run = json.loads((args.out / "run" / "run.json").read_text())
    periods = metrics["periods"]
    t_first = periods[0]["t_s"] if periods else 0.0
    per_minute: dict[int, list[dict]] = {}
    for p in periods:
        per_minute.setdefault(int((p["t_s"] - t_first) // 60), []).append(p)
    table = []
    resets_before = 0
    lat_minutes = run.get("latency_minutes", [])
    for minute, ps in sorted(per_minute.items()):
        lat = lat_minutes[minute]["written_ms"] if minute < len(lat_minutes) else {}
        table.append({"minute": minute, "hz": sum(p["hz"] for p in ps) / len(ps),
                      "resets": ps[-1]["resets"] - resets_before,
                      "ms_p50": worst(ps, "ms_median"), "ms_p95": worst(ps, "ms_p95"),
                      "ms_p99": worst(ps, "ms_p99"), "dropped_total": ps[-1]["dropped"],
                      "latency_p50": lat.get("p50"), "latency_p95": lat.get("p95"),
                      "latency_p99": lat.get("p99")})
        resets_before = ps[-1]["resets"]
    # RSS "at start": once the first statistics period is done (imports,
    # first key frames, zenoh session and thread stacks all in place).
    warm = next((r for t, r in samples if t >= 15.0), samples[0][1] if samples else None)
    # Also from the end of minute 1: bounded holdings fill during it (the map
    # up to map_max_mb, the malloc arenas to the working set), so growth past
    # it is what a leak would show.
    minute1 = next((r for t, r in samples if t >= 60.0), None)
    # The trend past minute 1 (least-squares slope), less sensitive to where
    # the two end samples happen to fall than their difference.
    late = [(t, r) for t, r in samples if t >= 60.0]
    slope = (float(np.polyfit([t for t, _ in late], [r for _, r in late], 1)[0]) * 60.0
             if len(late) >= 3 else None)
    report = {
        "minutes": args.minutes,
        "frames": metrics["frames"],
        "frames_dropped": metrics["frames_dropped"],
        "frame_hz": metrics["frame_hz"],
        "frame_ms_median": metrics["frame_ms_median"],
        "frame_ms_p95": metrics["frame_ms_p95"],
        "frame_ms_p99": metrics["frame_ms_p99"],
        "rss_start_mb": warm,
        "rss_end_mb": samples[-1][1] if samples else None,
        "rss_growth_mb": (samples[-1][1] - warm) if samples and warm else None,
        "rss_1min_mb": minute1,
        "rss_growth_after_1min_mb": (samples[-1][1] - minute1) if minute1 else None,
        "rss_trend_after_1min_mb_per_min": slope,
        "frames_late_at_source": metrics.get("frames_late_at_source"),
        "resets": run.get("resets"),
        "latency_ms": run.get("latency_ms"),
        "latency_capture_to_arrival_ms": run.get("latency_capture_to_arrival_ms"),
        "timesync": run.get("timesync"),
        "delay_advice": run.get("delay_advice"),
        "untrusted_sent": run.get("untrusted_sent"),
        "rss_samples": samples,
        "per_minute": table,
    }
    (args.out / "soak.json").write_text(json.dumps(report, indent=2) + "\n")
    print(f"\nsoak: {args.minutes:g} min, {metrics['frames']} frames at "
          f"{metrics['frame_hz']:.1f} Hz, dropped {metrics['frames_dropped']}, "
          f"late at the source {metrics.get('frames_late_at_source', 0)}")
    print(f"RSS {warm:.1f} MB after 15 s -> {samples[-1][1]:.1f} MB at the end "
          f"({report['rss_growth_mb']:+.1f} MB)")
    if minute1 is not None:
        print(f"RSS {minute1:.1f} MB after 60 s -> {samples[-1][1]:.1f} MB at the end "
              f"({report['rss_growth_after_1min_mb']:+.1f} MB)")
    if slope is not None:
        print(f"RSS trend after 60 s: {slope:+.2f} MB per minute")
    lat = run.get("latency_ms") or {}
    print(f"latency capture -> written: p50 {fmt(lat.get('p50'))} / p95 {fmt(lat.get('p95'))} "
          f"/ p99 {fmt(lat.get('p99'))} ms; resets {run.get('resets')}; "
          f"untrusted sent {run.get('untrusted_sent')}")
    adv = run.get("delay_advice") or {}
    ts = run.get("timesync") or {}
    print(f"delay advice: VISO_DELAY_MS {adv.get('VISO_DELAY_MS')}, EKF2_EV_DELAY "
          f"{adv.get('EKF2_EV_DELAY')} (from capture to {adv.get('basis')}); TIMESYNC round "
          f"trip {ts.get('rtt_min_ms')} ms")
    print("minute   Hz  resets  loop p50/p95/p99 ms (worst period)  latency p50/p95/p99 ms  "
          "dropped")
    for row in table:
        print(f"{row['minute']:>6} {row['hz']:5.1f} {row['resets']:6d}   "
              f"{fmt(row['ms_p50'])} / {fmt(row['ms_p95'])} / {fmt(row['ms_p99'])}"
              f"{'':18}{fmt(row['latency_p50'])} / {fmt(row['latency_p95'])} / "
              f"{fmt(row['latency_p99'])}  {row['dropped_total']:8d}")
    return 0


def fmt(v: float | None) -> str:
    return "  n/a" if v is None else f"{v:5.1f}"


if __name__ == "__main__":
    sys.exit(main())
