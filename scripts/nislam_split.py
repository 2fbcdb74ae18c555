"""Where NI-SLAM's frame-to-frame error comes from on a sequence with ground truth.

    .venv/bin/python scripts/nislam_split.py SEQ_DIR [--set KEY=VALUE ...] [--noise-deg X] [--seed N]

Replays SEQ_DIR (TUM layout, attitude from attitude.txt or the ground truth)
with NI-SLAM and splits the lag-1 translation error (docs/nislam-error-budget.md,
"The remaining error on tum_fr1_rpy, split"):
  - pairs of frames matched against the same key, and across key changes
    (a re-used kept key, or a new key);
  - the same-key lateral error (the tracker's increment against the key,
    t = (-du s, -dv s, t_z), against the true motion since the key's frame in
    the key's true axes) along and across the direction the frame-to-frame
    rotation moves the content ("flow": rotation x mean depth), by flow;
  - the error against the key per key axis (systematic; what new keys inherit);
  - per key: its cell size, the rate it was made at, the matched cells' mean
    depth, and its frames' same-key lateral (mm and cells) and axial error,
    with its share of the same-key squared error;
  - with --set depth_tilt_fit=true: the tilt of the depth differences and how
    much of it the rotation since the key, or the rates, explain.
--set overrides [nislam] parameters (numbers or true/false).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from nislam_experiment import parser, rms_mm, setup  # noqa: E402

import onboard.nislam.tracker as tracker_mod  # noqa: E402
from sim_replay.budget import KeyTimes  # noqa: E402


def main() -> int:
    ap = parser(__doc__.split("\n\n")[0])
    args = ap.parse_args()
    params, seq, att = setup(args)
    depth_of, tilt_of = {}, {}
    original = tracker_mod.depth_translation

    def depth_translation(*a, **k):  # the matched cells' mean key depth, per frame
        fit = original(*a, **k)
        depth_of["z"] = None if fit is None else fit.z_mean_m
        tilt_of["theta"] = None if fit is None else fit.theta_rad[:2]
        return fit

    tracker_mod.depth_translation = depth_translation
    tr = tracker_mod.NislamTracker(seq.intrinsics, params)
    rows, key_t, tilts = [], KeyTimes(), []
    for frame in seq.frames():
        r = tr.track(frame, att)
        key_t.add(r)
        if r.trusted and depth_of.get("z") is not None:
            rows.append((r, key_t.get(r.reference_keyframe_id, np.nan), depth_of["z"]))
            tilts.append(tilt_of["theta"])
    gt = seq.groundtruth
    sl = Slerp(gt.t_s, Rotation.from_quat(gt.q_xyzw))
    t = np.array([r.t_s for r, _, _ in rows])
    kt = np.array([k for _, k, _ in rows])
    ok = np.isfinite(kt) & (t >= gt.t_s[0]) & (t <= gt.t_s[-1]) & (kt >= gt.t_s[0])
    t, kt = t[ok], kt[ok]
    rows = [x for x, keep in zip(rows, ok) if keep]
    tilts = [x for x, keep in zip(tilts, ok) if keep]
    ref = np.array([r.reference_keyframe_id for r, _, _ in rows])

    def pos(ts):
        return np.stack([np.interp(ts, gt.t_s, gt.p_xyz_m[:, i]) for i in range(3)], axis=1)

    r_f, r_k = sl(t), sl(kt)
    est = np.array([r.p_W_m for r, _, _ in rows])
    true_p = pos(t)
    step = r_f[:-1].inv().apply((est[1:] - est[:-1]) - (true_p[1:] - true_p[:-1]))
    n = np.linalg.norm(step, axis=1)
    same = ref[1:] == ref[:-1]
    reused = np.array([r.keyframe_reused for r, _, _ in rows])[1:]
    print(f"{len(rows)} frames; lag-1 RPE {rms_mm(n):.2f} mm: same key {rms_mm(n[same]):.2f} "
          f"({same.sum()} pairs), key changes {rms_mm(n[~same]):.2f} ({(~same).sum()}: "
          f"re-used {rms_mm(n[~same & reused]):.2f} x {(~same & reused).sum()}, "
          f"new {rms_mm(n[~same & ~reused]):.2f} x {(~same & ~reused).sum()}); "
          f"share of the squared error at changes {np.sum(n[~same] ** 2) / np.sum(n ** 2):.2f}")
    meas = np.array([(-r.shift_cells[0] * r.res_m, -r.shift_cells[1] * r.res_m, r.tz_m)
                     for r, _, _ in rows])
    inc_err = meas - r_k.inv().apply(true_p - pos(kt))
    print("error against the key, key axes x / y / z: "
          + " / ".join(f"{rms_mm(inc_err[:, i]):.1f}" for i in range(3)) + " mm")
    i = np.flatnonzero(same) + 1
    de = inc_err[i] - inc_err[i - 1]
    w = (r_k[i].inv() * r_f[i] * r_f[i - 1].inv() * r_k[i]).as_rotvec()  # frame-to-frame, key axes
    z = np.array([d for _, _, d in rows])[i]
    flow = np.stack([w[:, 1], -w[:, 0]], axis=1) * z[:, None]
    fn = np.linalg.norm(flow, axis=1)
    u = flow / np.maximum(fn[:, None], 1e-12)
    along = np.sum(de[:, :2] * u, axis=1)
    across = de[:, 1] * u[:, 0] - de[:, 0] * u[:, 1]
    print(f"same-key lateral lag-1 {rms_mm(np.linalg.norm(de[:, :2], axis=1)):.2f} mm: along the "
          f"rotation's flow {rms_mm(along):.2f}, across {rms_mm(across):.2f}; axial {rms_mm(de[:, 2]):.2f}")
    print("| flow per frame | pairs | along mm | across mm | axial mm |\n|---|---|---|---|---|")
    for lo, hi in ((0.0, 0.02), (0.02, 0.04), (0.04, 0.07), (0.07, np.inf)):
        m = (fn >= lo) & (fn < hi)
        print(f"| {lo * 1e3:.0f}-{hi * 1e3:.0f} mm | {m.sum()} | {rms_mm(along[m]):.2f} | "
              f"{rms_mm(across[m]):.2f} | {rms_mm(de[m, 2]):.2f} |")
    _per_key(ref[i], kt[i], z, np.array([r.res_m for r, _, _ in rows])[i],
             np.array([r.psr for r, _, _ in rows])[i], de, sl)
    if params.depth_tilt_fit:
        rel = r_k.inv() * r_f  # the rotation since the key, key axes
        _tilt(np.array(tilts), rel, _rate(sl, kt), rel.apply(_rate(sl, t)))
    return 0


def _rate(sl: Slerp, t: np.ndarray) -> np.ndarray:
    """Body rate (rad/s, camera axes) over +-20 ms."""
    lo, hi = np.maximum(t - 0.02, sl.times[0]), np.minimum(t + 0.02, sl.times[-1])
    return (sl(lo).inv() * sl(hi)).as_rotvec() / np.maximum(hi - lo, 1e-9)[:, None]


def _tilt(theta: np.ndarray, rel: Rotation, w_key: np.ndarray, w_frame: np.ndarray) -> None:
    """With depth_tilt_fit: how much of the depth differences' tilt (a
    residual rotation about the key's x, y) the rotation since the key and
    the difference of the key's and the frame's rates explain (a linear fit)."""
    print("tilt of the depth differences: " + " / ".join(
        f"{np.degrees(np.sqrt(np.mean(theta[:, c] ** 2))):.2f}" for c in range(2)) + " deg RMS about x / y")
    for name, x in (("rotation since the key", rel.as_rotvec()), ("rate difference", w_frame - w_key)):
        a = np.c_[x, np.ones(len(x))]
        for c in range(2):
            coef = np.linalg.lstsq(a, theta[:, c], rcond=None)[0]
            r2 = 1.0 - np.sum((theta[:, c] - a @ coef) ** 2) / np.sum((theta[:, c] - theta[:, c].mean()) ** 2)
            print(f"  about {'xy'[c]}, by the {name}: R^2 {r2:.2f}, per rad (x, y, z) "
                  + ", ".join(f"{v:+.4f}" for v in coef[:3]))


def _per_key(ref: np.ndarray, kt: np.ndarray, z: np.ndarray, res: np.ndarray, psr: np.ndarray,
             de: np.ndarray, sl: Slerp) -> None:
    """The same-key steps by key: which keys carry the error, and at what
    cell size, depth and rate of making."""
    lat2 = np.sum(de[:, :2] ** 2, axis=1)
    total = float(np.sum(lat2 + de[:, 2] ** 2))
    print("| key | pairs | cell mm | made at deg/s | depth m | lateral mm | lateral cells | axial mm "
          "| median PSR | share |\n|---|---|---|---|---|---|---|---|---|---|")
    for k in np.unique(ref):
        m = ref == k
        rate = np.degrees(np.linalg.norm(_rate(sl, kt[m][:1])))
        lat = rms_mm(np.sqrt(lat2[m]))
        print(f"| {k} | {m.sum()} | {res[m][0] * 1e3:.1f} | {rate:.0f} | {np.median(z[m]):.2f} | "
              f"{lat:.2f} | {lat / (res[m][0] * 1e3):.2f} | {rms_mm(de[m, 2]):.2f} | "
              f"{np.median(psr[m]):.0f} | {float(np.sum(lat2[m] + de[m, 2] ** 2)) / total:.2f} |")


if __name__ == "__main__":
    sys.exit(main())
