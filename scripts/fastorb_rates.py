"""FastORB's body rate on a rolling-shutter sequence against the ground truth's.

    .venv/bin/python scripts/fastorb_rates.py SEQ_DIR [KEY=JSON ...]

Replays SEQ_DIR (TUM layout with groundtruth.txt, e.g. ../shared/data/tum_fr1_rpy)
through FastORB (KEY=JSON: config overrides, e.g. fastorb.rolling_shutter_settle_landmarks=false)
and prints, at the frames that made new landmarks and at all posed frames, the
error of rate estimates against the ground truth's (central difference of the
ground-truth poses at the frame stamps), camera axes, rad/s: the rate the rows'
shear measured (what landmarks are first made with), backward / central
differences of the tracker's poses (what landmark_rate.py settles them with),
and a quadratic fit over five poses; then the translation rate the shutter
correction makes landmarks with (the motion model's) against the poses'
central difference and zero (docs/fastorb_backend.md, "New landmarks settled
with the poses' rate", "The frame's own rate").
"""

from __future__ import annotations

import json
import sys

import numpy as np
from scipy.spatial.transform import Rotation

from onboard.app.bench import replay_attitude
from onboard.app.config import load_config
from onboard.core.rotations import so3_log
from onboard.fastorb.shutter import twist_rate
from onboard.fusion.registry import make_tracker
from sim_replay.tum import open_sequence


def main(seq_dir: str, overrides: list[str]) -> None:
    ov = {k: json.loads(v) for k, v in (kv.split("=", 1) for kv in overrides)}
    ov["tracker.name"] = "fastorb"
    cfg = load_config(None, ov)
    seq = open_sequence(seq_dir, cfg.replay.assoc_max_dt_s, cfg.replay.undistort,
                        cfg.replay.stamp_window_s)
    att, _ = replay_attitude(seq, cfg)
    tr = make_tracker("fastorb", seq.intrinsics, cfg)
    made: set[int] = set()
    frame = {"i": 0}
    landmarks = tr._landmarks

    def logged(*a):  # which frames make landmarks
        made.add(frame["i"])
        return landmarks(*a)

    tr._landmarks = logged
    T, tm, shear, ts, rho = [], [], [], [], []
    for i, fr in enumerate(seq.frames()):
        frame["i"] = i
        r = tr.track(fr, att)
        T.append(tr._history[-1][1].copy() if r.trusted and tr._history else None)
        tm.append(tr._t_motion)
        shear.append(None if tr._rate is None else tr._rate.copy())
        rho.append(tr._xi[3:].copy() if r.trusted else None)  # what landmarks are made with
        ts.append(fr.t_s)
        tr.backend_step()
    ts = np.array(ts)
    p, q, ok = seq.groundtruth.interpolate(ts, cfg.replay.gt_max_gap_s)
    G = [None if not ok[k] else np.block([[Rotation.from_quat(q[k]).as_matrix().T,
                                          -(Rotation.from_quat(q[k]).as_matrix().T @ p[k])[:, None]],
                                         [np.zeros((1, 3)), np.ones((1, 1))]]) for k in range(len(ts))]
    n = len(ts)

    def diff(P, times, a, b, part=slice(0, 3)):
        if a < 0 or b >= n or P[a] is None or P[b] is None:
            return None
        return twist_rate(P[a], P[b], times[b] - times[a])[part]

    def fit(k, h=2):
        xs = [j for j in range(k - h, k + h + 1) if 0 <= j < n and j != k and T[j] is not None]
        if T[k] is None or len(xs) < 2:
            return None
        A = np.array([[tm[j] - tm[k], 0.5 * (tm[j] - tm[k]) ** 2] for j in xs])
        Y = np.array([so3_log(T[j][:3, :3] @ T[k][:3, :3].T) for j in xs])
        return np.linalg.lstsq(A, Y, rcond=None)[0][0]

    rates = {"rows' shear": lambda k: shear[k],
             "poses, backward difference": lambda k: diff(T, tm, k - 1, k),
             "poses, central difference": lambda k: diff(T, tm, k - 1, k + 1),
             "poses, central over 4 frames": lambda k: diff(T, tm, k - 2, k + 2),
             "poses, quadratic fit over 5": fit}
    for name, frames in (("frames that made landmarks", sorted(made)),
                         ("posed frames", [k for k in range(n) if T[k] is not None])):
        print(f"{name}: {len(frames)}")
        for label, f in rates.items():
            E = np.array([e for e in (_err(f(k), diff(G, ts, k - 1, k + 1)) for k in frames)
                          if e is not None])
            print(f"  {label:30s} RMS x/y/z {np.sqrt(np.mean(E**2, 0)).round(3)} mean "
                  f"{E.mean(0).round(3)} norm RMS {np.sqrt(np.mean(np.sum(E**2, 1))):.3f} rad/s")
    # The translation rate rho (camera axes, m/s) the shutter correction uses:
    # the motion model's (the last interval's) against the poses' central
    # difference, both against the ground truth's (docs/fastorb_backend.md).
    tr_ = slice(3, 6)
    trans = {"motion model's (last interval)": lambda k: rho[k],
             "poses, central difference": lambda k: diff(T, tm, k - 1, k + 1, tr_),
             "zero": lambda k: np.zeros(3) if T[k] is not None else None}
    frames = sorted(made)
    truth = [diff(G, ts, k - 1, k + 1, tr_) for k in frames]
    print("translation rate at frames that made landmarks: ground truth RMS "
          f"{np.sqrt(np.mean(np.array([g for g in truth if g is not None])**2, 0)).round(3)} m/s")
    for label, f in trans.items():
        E = np.array([e for e in (_err(f(k), g) for k, g in zip(frames, truth)) if e is not None])
        print(f"  {label:30s} RMS x/y/z {np.sqrt(np.mean(E**2, 0)).round(3)} m/s")


def _err(est, truth):
    return None if est is None or truth is None else est - truth


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
