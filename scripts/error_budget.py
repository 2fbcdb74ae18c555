"""Per-frame error budget of NI-SLAM on synthetic flights: one error source at a time.

    .venv/bin/python scripts/error_budget.py [--scenario figure8 ...] [--seconds 20] [--seed 7]
                                            [--work DIR] [--sources NAME ...] [--seq DIR ...]

Renders each flight once per camera model into --work (kept and re-used: the
same seed writes the same bytes), replays it with one source of error switched
on (sim_replay/budget.py lists them) and prints a markdown table; --seq scores
recorded sequences with the defaults instead. Columns: see
sim_replay.budget.score_flight and docs/nislam-error-budget.md.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sim_replay.budget import SOURCES, render_flight, score_flight  # noqa: E402


def _row(flight: str, name: str, r: dict) -> str:
    return (f"| {flight} | {name} | {r['rpe1'] * 1e3:.2f} | {r['lat'] * 1e3:.2f} | "
            f"{r['ax'] * 1e3:.2f} | {r['rpe10'] * 1e3:.2f} | {r['jump'] * 1e3:.2f} | "
            f"{r['ate'] * 1e3:.1f} | {r['ratio']:.2f} | {100 * r['tracked']:.0f} | {r['keys']} | "
            f"{r['res_mm']:.1f} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", nargs="*", default=["figure8", "yaw-spin", "aggressive"])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "nislam_budget")
    ap.add_argument("--sources", nargs="*", default=list(SOURCES), metavar="NAME")
    ap.add_argument("--seq", nargs="*", type=Path, default=[], metavar="DIR",
                    help="also score these recorded sequences (defaults, exact attitude)")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    print("| flight | source | rpe1 mm | lat mm | ax mm | rpe10 mm | jump mm | ATE mm | "
          "path ratio | tracked % | keys new/changes | cell mm |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for seq in args.seq:
        print(_row(seq.name, "defaults", score_flight(seq)), flush=True)
    for scen in args.scenario:
        for name in args.sources:
            camera, att, nis = SOURCES[name]
            seq = render_flight(scen, camera, args.seconds, args.seed, args.work)
            print(_row(scen, name, score_flight(seq, att, nis, args.seed)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
