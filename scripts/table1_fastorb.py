#!/usr/bin/env python3
"""FastORB-SLAM's Table I experiment on our data: keypoint matching between
frame pairs with and without the motion-model seeding.

For a reference frame r and the frame c = r + gap:
  1. ORB keypoints (detection only, up to orb_features) on the equalised r,
     their landmarks from r's depth and r's pose;
  2. pyramid LK from r to c, either from the keypoints' own positions (KLT,
     the paper's "w/o UAM") or from the landmarks projected with the pose the
     uniform-acceleration model predicts from frames r - 2 gap, r - gap, r
     (Eqs. 14-16, "w/ UAM"); the same pyramid and termination rule for both;
  3. verification: grid motion statistics, then RANSAC on the fundamental
     matrix. Ratio = matches left after verification / keypoints detected
     (the paper's N_inlier / N_Total); Time = the verification time.

The poses feeding the motion model are the FastORB tracker's own estimates,
as in the paper; they come from one tracker run over the sequence first.

    .venv/bin/python scripts/table1_fastorb.py [SEQ_DIR] [--gaps 1,2,3] [--every 5]
    .venv/bin/python scripts/table1_fastorb.py --synthetic aggressive --seconds 10

SEQ_DIR defaults to ../shared/data/tum_fr1_rpy. `--synthetic SCENARIO` first
renders a flight with `sim_replay.sim.simulate` into a temporary folder.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from onboard.app.config import load_config
from onboard.core.messages import RgbdFrame
from onboard.core.se3 import make_pose
from onboard.fastorb.local_map import sample_depth
from onboard.fastorb.matching import LkSettings, epipolar_inliers, gms_inliers, track_lk
from onboard.fastorb.motion import back_project, predict_uam, project
from onboard.fastorb.params import FastOrbParams
from onboard.fastorb.tracker import FastOrbTracker
from sim_replay.tum import open_sequence

DEFAULT_SEQ = REPO.parent / "shared" / "data" / "tum_fr1_rpy"


@dataclass
class PairResult:
    ref: int
    gap: int
    keypoints: int
    ratio: dict[str, float]  # "klt" / "uam": verified matches / keypoints
    verify_ms: dict[str, float]  # GMS + epipolar RANSAC
    epipolar_ms: dict[str, float]  # the RANSAC alone
    lk_ms: dict[str, float]


class NoAttitude:
    def rotation_at(self, t_s: float) -> None:
        return None


def tracker_poses(frames: list[RgbdFrame], tracker: FastOrbTracker) -> list[np.ndarray | None]:
    """T_cw per frame from a tracker run (None where it had no pose)."""
    out: list[np.ndarray | None] = []
    for f in frames:
        r = tracker.track(f, NoAttitude())
        if r.trusted:
            R_cw = r.R_W_C.T
            out.append(make_pose(R_cw, -R_cw @ r.p_W_m))
        else:
            out.append(None)
    return out


def run_pair(
    gray_r: np.ndarray,
    gray_c: np.ndarray,
    depth_r: np.ndarray,
    poses: list[np.ndarray],
    K: np.ndarray,
    p: FastOrbParams,
    orb: cv2.ORB,
) -> tuple[int, dict[str, tuple[float, float, float, float]]]:
    """(keypoints, {variant: (ratio, verify_ms, epipolar_ms, lk_ms)}) for one pair;
    `poses` are T_cw of frames r - 2 gap, r - gap, r."""
    uv = np.array([k.pt for k in orb.detect(gray_r, None)], np.float64).reshape(-1, 2)
    n = len(uv)
    z = sample_depth(depth_r, uv, p.min_depth_m, p.max_depth_m, p.depth_edge_rel)
    has = z > 0
    prior = predict_uam([0.0, 1.0, 2.0], poses, 3.0, p.uam_accel_gain)  # Eqs. 14-15
    guess = uv.copy()
    xyz = back_project(K, poses[-1], uv[has], z[has])
    seeded, zc = project(K, prior, xyz)  # Eq. 16
    guess[np.flatnonzero(has)[zc > 1e-3]] = seeded[zc > 1e-3]
    lk = LkSettings(p.lk_win_px, p.lk_max_level, p.lk_max_iter, p.lk_eps_px, p.lk_max_error,
                    p.lk_min_eigen)
    size = (gray_r.shape[1], gray_r.shape[0])
    out = {}
    for name, start in (("klt", None), ("uam", guess)):
        t0 = time.perf_counter()
        moved, ok = track_lk(gray_r, gray_c, uv, start, lk)
        t1 = time.perf_counter()
        idx = np.flatnonzero(ok)
        idx = idx[gms_inliers(uv[idx], moved[idx], size, (p.gms_grid_cols, p.gms_grid_rows),
                              p.gms_alpha)]
        t2 = time.perf_counter()
        keep = epipolar_inliers(uv[idx], moved[idx], p.epipolar_threshold_px,
                                p.epipolar_confidence)
        t3 = time.perf_counter()
        out[name] = (keep.sum() / max(n, 1), (t3 - t1) * 1e3, (t3 - t2) * 1e3, (t1 - t0) * 1e3)
    return n, out


def experiment(
    frames: list[RgbdFrame],
    K: np.ndarray,
    p: FastOrbParams,
    poses: list[np.ndarray | None],
    gaps: list[int],
    every: int,
) -> list[PairResult]:
    clahe = cv2.createCLAHE(p.clahe_clip_limit, (p.clahe_tiles, p.clahe_tiles))
    orb = cv2.ORB_create(nfeatures=p.orb_features, scaleFactor=p.orb_scale_factor,
                         nlevels=p.orb_levels, fastThreshold=p.orb_fast_threshold)
    gray = [clahe.apply(cv2.cvtColor(f.bgr, cv2.COLOR_BGR2GRAY)) for f in frames]
    results = []
    for gap in gaps:
        for r in range(2 * gap, len(frames) - gap, every):
            trio = [poses[r - 2 * gap], poses[r - gap], poses[r]]
            if any(T is None for T in trio):
                continue
            n, out = run_pair(gray[r], gray[r + gap], frames[r].depth_m, trio, K, p, orb)
            results.append(PairResult(
                r, gap, n,
                {k: v[0] for k, v in out.items()}, {k: v[1] for k, v in out.items()},
                {k: v[2] for k, v in out.items()}, {k: v[3] for k, v in out.items()},
            ))
    return results


def summary(results: list[PairResult], gaps: list[int]) -> list[dict]:
    """Per gap: mean ratios and their 10th percentile; median times (the
    paper averages, but a shared machine that pauses for hundreds of ms
    would decide a mean)."""
    rows = []
    for gap in gaps + [0]:
        sel = [r for r in results if gap == 0 or r.gap == gap]
        if not sel:
            continue
        row = {"gap": "all" if gap == 0 else gap, "pairs": len(sel),
               "keypoints": float(np.mean([r.keypoints for r in sel]))}
        for v in ("klt", "uam"):
            row[f"{v}_ratio"] = float(np.mean([r.ratio[v] for r in sel]))
            row[f"{v}_ratio_p10"] = float(np.percentile([r.ratio[v] for r in sel], 10))
            row[f"{v}_verify_ms"] = float(np.median([r.verify_ms[v] for r in sel]))
            row[f"{v}_epipolar_ms"] = float(np.median([r.epipolar_ms[v] for r in sel]))
            row[f"{v}_lk_ms"] = float(np.median([r.lk_ms[v] for r in sel]))
        rows.append(row)
    return rows


def print_table(title: str, rows: list[dict]) -> None:
    print(title)
    print("gap   pairs  kps  | KLT (w/o UAM): ratio (p10)  verify ms (RANSAC)  LK ms "
          "| ours (w/ UAM): ratio (p10)  verify ms (RANSAC)  LK ms")
    for r in rows:
        print(
            f"{str(r['gap']):>4} {r['pairs']:6d} {r['keypoints']:5.0f} |"
            f"       {r['klt_ratio']:.3f} ({r['klt_ratio_p10']:.3f})   "
            f"{r['klt_verify_ms']:5.2f} ({r['klt_epipolar_ms']:4.2f})      {r['klt_lk_ms']:5.2f} |"
            f"       {r['uam_ratio']:.3f} ({r['uam_ratio_p10']:.3f})   "
            f"{r['uam_verify_ms']:5.2f} ({r['uam_epipolar_ms']:4.2f})      {r['uam_lk_ms']:5.2f}"
        )


def load_sequence(seq_dir: Path, cfg) -> tuple[list[RgbdFrame], np.ndarray]:
    seq = open_sequence(seq_dir, cfg.replay.assoc_max_dt_s, cfg.replay.undistort)
    frames = seq.load_all()
    i = seq.intrinsics
    K = np.array([[i.fx, 0.0, i.cx], [0.0, i.fy, i.cy], [0.0, 0.0, 1.0]])
    return frames, K


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("seq_dir", nargs="?", type=Path, default=DEFAULT_SEQ)
    ap.add_argument("--config", type=Path, help="config file ([fastorb] section)")
    ap.add_argument("--gaps", default="1,2,3", help="frame gaps r -> r + gap (default 1,2,3)")
    ap.add_argument("--every", type=int, default=5, help="a reference frame every n frames")
    ap.add_argument("--synthetic", metavar="SCENARIO",
                    help="render this sim_replay scenario first and use it instead")
    ap.add_argument("--seconds", type=float, default=10.0, help="synthetic flight length")
    ap.add_argument("--json", action="store_true", help="print the summary as JSON")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)  # one core, as bench and the onboard loop
    cfg = load_config(args.config)
    gaps = [int(g) for g in args.gaps.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        seq_dir = args.seq_dir
        if args.synthetic:
            from sim_replay.sim import sim_options, simulate

            seq_dir = Path(tmp) / args.synthetic
            simulate(args.synthetic, seq_dir, sim_options(seconds=args.seconds), progress=False)
        frames, K = load_sequence(seq_dir, cfg)
    intr = open_sequence_intrinsics(K, frames)
    poses = tracker_poses(frames, FastOrbTracker(intr, cfg.fastorb))
    results = experiment(frames, K, cfg.fastorb, poses, gaps, args.every)
    rows = summary(results, gaps)
    name = args.synthetic or Path(args.seq_dir).name
    if args.json:
        print(json.dumps({"sequence": name, "rows": rows}, indent=2))
    else:
        tracked = sum(T is not None for T in poses)
        print_table(f"Table I on {name}: {len(frames)} frames, {tracked} posed by FastORB; "
                    f"ratio = verified / detected, ms: median per pair (one core)", rows)
    return 0


def open_sequence_intrinsics(K: np.ndarray, frames: list[RgbdFrame]):
    from onboard.core.camera import CameraIntrinsics

    h, w = frames[0].depth_m.shape
    return CameraIntrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h)


if __name__ == "__main__":
    sys.exit(main())
