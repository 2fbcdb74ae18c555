"""Judge a change on everything we have: every tracker on tum_fr1_rpy (exact
and 1-deg-noisy attitude) and on every synthetic flight with a perfect and a
myAHRS+ attitude, as one markdown table of ATE, frame-lag RPE, path ratio,
tracked share and resets.

    .venv/bin/python scripts/scorecard.py --work /tmp/scorecard [--jobs 2]
        [--trackers nislam fastorb fused] [--flights circle figure8 ...] [--config C.toml]

Flights are rendered once into --work (`nislam sim NAME --seconds 20 --seed 7`)
and reused; each replay writes its folder there too. Errors and counts do not
depend on the machine's load, times do (none are printed here: use
`nislam bench`).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
NISLAM = [str(Path(sys.executable).parent / "nislam")]  # the venv's entry point
TUM = REPO.parent / "shared" / "data" / "tum_fr1_rpy"
FLIGHTS = ("circle", "corridor", "aggressive", "figure8", "yaw-spin", "blank-turn")
PROFILES = ("perfect", "myahrs")
TRACKERS = ("nislam", "fastorb", "fused")


def render(work: Path, flight: str, profile: str) -> Path:
    out = work / "flights" / f"{flight}_{profile}"
    if not (out / "metrics_sim.done").exists():
        subprocess.run([*NISLAM, "sim", flight, "--seconds", "20", "--seed", "7",
                        "--ahrs-profile", profile, "--out", str(out), "--quiet"],
                       check=True, stdout=subprocess.DEVNULL)
        (out / "metrics_sim.done").touch()
    return out


def replay(work: Path, seq: Path, label: str, tracker: str, extra: list[str]) -> dict:
    out = work / "runs" / f"{label}_{tracker}"
    subprocess.run([*NISLAM, "replay", str(seq), "--tracker", tracker, "--out", str(out),
                    "--quiet", *extra], check=True, stdout=subprocess.DEVNULL)
    m = json.loads((out / "metrics.json").read_text())
    m["label"] = label
    return m


def row(m: dict) -> str:
    def mm(key: str) -> str:
        v = m.get(key)
        return "-" if v is None else f"{1e3 * v:.1f}"

    lags = " / ".join(mm(f"rpe_lag{k}_m") for k in (1, 3, 10, 30))
    ratio = m.get("path_length_ratio")
    return (f"| {m['label']} | {m['tracker']} | {mm('ate_rmse_m')} | {lags} | "
            f"{'-' if ratio is None else f'{ratio:.2f}'} | {100 * m['tracked_share']:.1f} | "
            f"{m['resets']} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True, help="folder for flights and runs")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--trackers", nargs="+", default=list(TRACKERS), choices=TRACKERS)
    ap.add_argument("--flights", nargs="+", default=list(FLIGHTS), choices=FLIGHTS)
    ap.add_argument("--no-tum", action="store_true", help="synthetic flights only")
    ap.add_argument("--config", type=Path, help="a TOML config for every replay (a setting tried)")
    args = ap.parse_args()

    with ThreadPoolExecutor(args.jobs) as pool:
        seqs = {f"{f} {p}": pool.submit(render, args.work, f, p)
                for f in args.flights for p in PROFILES}
        cases = [] if args.no_tum else [("tum_fr1_rpy", TUM, [])]
        if not args.no_tum:
            cases.append(("tum_fr1_rpy noise 1 deg", TUM, ["--attitude-noise-deg", "1", "--seed", "1"]))
        cases += [(label, fut.result(), []) for label, fut in seqs.items()]
        common = [] if args.config is None else ["--config", str(args.config)]
        jobs = [pool.submit(replay, args.work, seq, label.replace(" ", "_"), t, extra + common)
                for label, seq, extra in cases for t in args.trackers
                if not (t == "fastorb" and "noise" in label)]  # FastORB reads no attitude
        results = [j.result() for j in jobs]
    print("| sequence | tracker | ATE mm | RPE lag 1 / 3 / 10 / 30 mm | path ratio | tracked % | resets |")
    print("|---|---|---|---|---|---|---|")
    for m in results:
        print(row(m))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
