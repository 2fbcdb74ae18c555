"""How honest the ODOMETRY velocity covariance is: each tracker's results
(recorded with `scripts/fusion_cache.py record`, the fused tracker replayed on
them) go through the MAVLink feed (onboard.outputs.mavlink_feed.VisionFeed,
LOCAL_FRD = W), and the displacement it differenced, v_L * dt over the
window from the reference pose to this one, is compared with the true one.

    python scripts/velocity_cov.py CACHE.pkl [CACHE2.pkl ...] [--window 0.1]

Per tracker: windows scored, 1-sigma coverage of the displacement error per
(window, axis) (68 % for a consistent Gaussian), RMS error / RMS claimed sd,
the RMS and median |error| and the median claimed sd [mm] and that sd in the first and the
last 3 s of the flight (whether it grows with the drift).
"""

from __future__ import annotations

import argparse
import pickle
import sys
from pathlib import Path

import numpy as np

from onboard.core.evaluation import ground_truth_at
from onboard.outputs.mavlink_feed import VisionFeed

sys.path.insert(0, str(Path(__file__).parent))
from fusion_cache import TRACKERS, FusionParams, fuse  # noqa: E402


def displacements(results: list, window_s: float) -> tuple[np.ndarray, ...]:
    """(t_k, t_ref, displacement (3,), claimed variance (3,)) per sent velocity."""
    feed = VisionFeed(np.eye(3), velocity_window_s=window_s)
    rows = []
    for r in results:
        ev = feed.update(r)
        s = ev.sample
        if s is None or not np.all(np.isfinite(s.v_L_m_s)):
            continue
        ref = feed._history[0]  # the pose the velocity was differenced against
        dt = r.t_s - ref.t_s
        rows.append((r.t_s, ref.t_s, s.v_L_m_s * dt, s.v_var_L * dt**2))
    t = np.array([x[0] for x in rows])
    t0 = np.array([x[1] for x in rows])
    d = np.array([x[2] for x in rows]).reshape(-1, 3)
    var = np.array([x[3] for x in rows]).reshape(-1, 3)
    return t, t0, d, var


def score(results: list, gt, window_s: float) -> dict[str, float]:
    t, t0, d, var = displacements(results, window_s)
    g1, ok1 = ground_truth_at(t, gt, 0.1)
    g0, ok0 = ground_truth_at(t0, gt, 0.1)
    p1 = np.full((len(t), 3), np.nan)
    p0 = np.full((len(t), 3), np.nan)
    p1[ok1], p0[ok0] = g1.p_xyz_m, g0.p_xyz_m
    ok = np.all(np.isfinite(p1 - p0), axis=1) & np.all(np.isfinite(var), axis=1)
    e = d[ok] - (p1 - p0)[ok]
    sd = np.sqrt(var[ok])
    tt = t[ok] - t[0]
    first, last = tt <= 3.0, tt >= tt[-1] - 3.0
    return {
        "n": int(ok.sum()),
        "cov": float(np.mean(np.abs(e) <= sd)),
        "ratio": float(np.sqrt(np.mean(e**2)) / np.sqrt(np.mean(sd**2))),
        "rms_e": float(np.sqrt(np.mean(e**2))),
        "med_e": float(np.median(np.abs(e))),
        "med_sd": float(np.median(sd)),
        "sd_first": float(np.median(sd[first])),
        "sd_last": float(np.median(sd[last])),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("caches", nargs="+")
    ap.add_argument("--window", type=float, default=0.1, help="velocity_window_s [s]")
    a = ap.parse_args()
    print(f"{'sequence':22s} {'tracker':8s} {'n':>4s} {'cov':>5s} {'err/sd':>6s} {'rms err':>8s} "
          f"{'med|err|':>8s} {'med sd':>7s} {'sd 0-3s':>8s} {'sd last 3s':>10s}  [mm]")
    for path in a.caches:
        with open(path, "rb") as fh:
            cache = pickle.load(fh)
        runs = {n: cache["results"][n] for n in TRACKERS}
        runs["fused"] = fuse(cache, FusionParams())[0]
        for name, results in runs.items():
            s = score(results, cache["groundtruth"], a.window)
            print(f"{Path(path).stem:22s} {name:8s} {s['n']:4d} {100 * s['cov']:4.0f}% {s['ratio']:6.2f} "
                  f"{1e3 * s['rms_e']:8.2f} {1e3 * s['med_e']:8.2f} {1e3 * s['med_sd']:7.2f} {1e3 * s['sd_first']:8.2f} "
                  f"{1e3 * s['sd_last']:10.2f}")


if __name__ == "__main__":
    main()
