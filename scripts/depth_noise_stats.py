"""How a recording's depth errs on flat surfaces: steps between neighbouring
pixels and the noise's spatial correlation, by distance.

    .venv/bin/python scripts/depth_noise_stats.py SEQ_DIR [SEQ_DIR ...] [--every 10]

For every 32 x 32 patch of a depth image that is fully valid and flat (a
plane fitted to its depth leaves an RMS residual under 2 disparity steps
and the plane's own slope is under a quarter step per pixel), by the patch's
mean depth (1, 2, 3, 4 m +- 10 %):
  steps      share of horizontally neighbouring pixel pairs whose depths differ
             by 0, by one disparity step (+-0.6 of it), and by some other amount
             (neither: depth not quantised to disparity steps)
  sd         the residual's RMS, in disparity steps of the patch's depth
             (Kinect v1: step = z^2 / (f B) / 8, f B = 580 px x 0.075 m)
  corr k     correlation of the residual with itself k pixels along the row
             (a matcher's window makes neighbours err together)
The step is that of a Kinect v1 (`sim_replay.sensors.KINECT_V1`), so the
numbers of a recording and of a synthetic flight read on the same scale.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sim_replay.sensors import KINECT_V1  # noqa: E402

PATCH = 32
BANDS_M = (1.0, 2.0, 3.0, 4.0)
LAGS = (1, 2, 4, 8, 16)


def _depth_files(seq: Path) -> list[Path]:
    lines = (seq / "depth.txt").read_text().splitlines()
    return [seq / ln.split()[1] for ln in lines if ln.strip() and not ln.startswith("#")]


def _depth_scale(seq: Path) -> float:
    cam = seq / "camera.toml"
    if cam.exists():
        for ln in cam.read_text().splitlines():
            if ln.startswith("depth_scale"):
                return float(ln.split("=")[1])
    return 5000.0  # TUM


def patch_stats(z: np.ndarray, unit_m: float) -> dict | None:
    """Statistics of one patch (metres), None if it is not a flat, full patch."""
    if not (z > 0).all():
        return None
    zm = float(z.mean())
    step = KINECT_V1.depth_step_m(zm)
    yy, xx = np.mgrid[0:PATCH, 0:PATCH]
    a = np.column_stack([np.ones(z.size), xx.ravel(), yy.ravel()])
    coef, *_ = np.linalg.lstsq(a, z.ravel(), rcond=None)
    res = (z.ravel() - a @ coef).reshape(z.shape)
    sd = float(res.std())
    if sd > 2 * step or max(abs(coef[1]), abs(coef[2])) > 0.25 * step:
        return None
    d = np.abs(np.diff(z, axis=1)).ravel()
    tol = max(0.6 * step, 1.5 * unit_m)  # the PNG's unit rounds a step too
    zero = d < 0.5 * unit_m
    one = ~zero & (np.abs(d - step) < 0.4 * step) & (np.abs(d - step) <= tol)
    corr = []
    for k in LAGS:
        u, v = res[:, :-k].ravel(), res[:, k:].ravel()
        corr.append(float(np.mean(u * v) / max(np.mean(res * res), 1e-30)))
    return {"z": zm, "zero": zero.mean(), "one": one.mean(), "other": 1 - zero.mean() - one.mean(),
            "sd_steps": sd / step, "corr": corr}


def sequence_stats(seq: Path, every: int) -> dict[float, dict]:
    scale = _depth_scale(seq)
    acc: dict[float, list[dict]] = {b: [] for b in BANDS_M}
    for f in _depth_files(seq)[::every]:
        raw = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if raw is None:
            continue
        z = raw.astype(np.float64) / scale
        h, w = z.shape
        for r in range(0, h - PATCH + 1, PATCH):
            for c in range(0, w - PATCH + 1, PATCH):
                p = z[r:r + PATCH, c:c + PATCH]
                zm = float(p.mean())
                band = next((b for b in BANDS_M if abs(zm - b) <= 0.1 * b), None)
                if band is None:
                    continue
                s = patch_stats(p, 1.0 / scale)
                if s is not None:
                    acc[band].append(s)
    out = {}
    for b, rows in acc.items():
        if not rows:
            continue
        out[b] = {"patches": len(rows),
                  **{k: float(np.mean([r[k] for r in rows])) for k in ("zero", "one", "other")},
                  "sd_steps": float(np.sqrt(np.mean([r["sd_steps"] ** 2 for r in rows]))),
                  "corr": np.mean([r["corr"] for r in rows], axis=0).tolist()}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("seqs", nargs="+", type=Path)
    ap.add_argument("--every", type=int, default=10, help="every Nth depth frame (default 10)")
    args = ap.parse_args()
    print("| recording | depth | patches | step mm | same | one step | other | sd (steps) | "
          + " | ".join(f"corr {k}" for k in LAGS) + " |")
    print("|---" * (8 + len(LAGS)) + "|")
    for seq in args.seqs:
        for b, s in sequence_stats(seq, args.every).items():
            print(f"| {seq.name} | {b:.0f} m | {s['patches']} | {KINECT_V1.depth_step_m(b) * 1e3:.1f} | "
                  f"{s['zero']:.2f} | {s['one']:.2f} | {s['other']:.2f} | {s['sd_steps']:.2f} | "
                  + " | ".join(f"{c:.2f}" for c in s["corr"]) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
