"""The AHRS-to-camera time-offset calibration against the true offset on
synthetic flights (a script, not a test).

    python scripts/offset_calibration.py [--flight DIR ...] [--offsets-ms -30,0,30]
                                         [--profiles myahrs,autopilot] [--seeds 0,1]

Each flight (default: a 20 s `circle` rendered at 320x240 into
results/offset_calibration/) is decoded into memory once; then for every AHRS
profile of the simulator (sim_replay.sensors.AHRS_PROFILES: white noise plus
bias random walk), every offset and every seed, a fresh NI-SLAM tracker runs
over it with that attitude error (the profile's own offset replaced by the
one under test) and the estimate it settled on is compared with the truth.
Prints a table and writes offset_calibration.json into --out.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
NISLAM = REPO / ".venv" / "bin" / "nislam"


def main() -> int:
    from onboard.app.bench import pin_one_core
    from onboard.app.config import load_config
    from onboard.fusion.registry import make_tracker
    from sim_replay.attitude import AttitudeErrorModel, attitude_for_replay
    from sim_replay.sensors import AHRS_PROFILES
    from sim_replay.tum import open_sequence

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--flight", type=Path, action="append",
                    help="TUM-layout flight with exact attitude (default: render circle)")
    ap.add_argument("--offsets-ms", default="-30,0,30")
    ap.add_argument("--profiles", default="myahrs,autopilot")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--config", type=Path, help="TOML config (default: built-in)")
    ap.add_argument("--out", type=Path, default=REPO / "results" / "offset_calibration")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    flights = args.flight
    if not flights:
        flight = args.out / "circle"
        if not (flight / "rgb.txt").exists():
            subprocess.run([str(NISLAM), "sim", "circle", "--seconds", "20", "--width", "320",
                            "--height", "240", "--out", str(flight), "--quiet"], check=True)
        flights = [flight]
    offsets = [float(x) for x in args.offsets_ms.split(",")]
    profiles = args.profiles.split(",")
    seeds = [int(x) for x in args.seeds.split(",")]
    cfg = load_config(args.config)
    pin_one_core()
    rows = []
    for flight in flights:
        seq = open_sequence(flight, cfg.replay.assoc_max_dt_s, cfg.replay.undistort)
        frames = seq.load_all()
        for name in profiles:
            prof = AHRS_PROFILES[name]
            for offset_ms in offsets:
                for seed in seeds:
                    model = AttitudeErrorModel(prof["noise_deg"], prof["bias_deg_per_sqrt_s"],
                                               offset_ms, seed)
                    attitude, _ = attitude_for_replay(seq, model, cfg.replay.gt_max_gap_s)
                    tracker = make_tracker("nislam", seq.intrinsics, cfg)
                    track = [tracker.track(f, attitude) for f in frames]
                    est = np.array([r.attitude_offset_s for r in track]) * 1e3
                    last_s = frames[-1].t_s - frames[0].t_s
                    tail = est[len(est) * 3 // 4:]  # the last quarter: settled
                    row = {"flight": flight.name, "profile": name, "seed": seed,
                           "true_ms": offset_ms, "estimate_ms": float(est[-1]),
                           "error_ms": float(est[-1] - offset_ms),
                           "last_quarter_mean_ms": float(tail.mean()),
                           "last_quarter_spread_ms": float(tail.max() - tail.min()),
                           "tracked": sum(r.trusted for r in track), "frames": len(track),
                           "seconds": last_s}
                    rows.append(row)
                    print(f"{flight.name:>10} {name:>9} seed {seed}  true {offset_ms:+6.1f} ms  "
                          f"estimate {row['estimate_ms']:+6.1f} ms  error "
                          f"{row['error_ms']:+5.1f} ms  (last quarter {row['last_quarter_mean_ms']:+.1f}"
                          f", spread {row['last_quarter_spread_ms']:.1f})  tracked "
                          f"{row['tracked']}/{row['frames']}", flush=True)
    worst = max(abs(r["error_ms"]) for r in rows)
    print(f"worst |error| {worst:.1f} ms over {len(rows)} runs")
    (args.out / "offset_calibration.json").write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
