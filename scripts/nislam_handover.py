"""Where NI-SLAM's error at key changes comes from (issue 17, the hand-over).

    .venv/bin/python scripts/nislam_handover.py SEQ_DIR [--set KEY=VALUE ...] [--noise-deg X] [--seed N]

Replays SEQ_DIR (TUM layout or a synthetic flight) with NI-SLAM, exact or
noisy attitude, and splits the lag-1 translation error at each change of the
key a pose was measured against into
  - the keys' own position error (the new reference key's position, as the
    map holds it after the frame, against the old one's before it), and
  - the measurement against the key (the increment t = (-du s, -dv s, t_z)
    against the true motion since the key's frame, in the key's true axes),
for re-used kept keys and for new keys separately, and prints the error of
the keys' positions (against the truth at their frames, the first frame's
position subtracted as the tracker's world starts there).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from nislam_experiment import parser, rms_mm, setup  # noqa: E402

from onboard.core.evaluation import evaluate, ground_truth_at  # noqa: E402
from onboard.core.trajectory import Trajectory  # noqa: E402
from onboard.nislam.tracker import NislamTracker  # noqa: E402


def _keys(tr: NislamTracker) -> dict[int, tuple[float, np.ndarray]]:
    keys = {k.keyframe_id: (k.t_s, k.p_W_m.copy()) for k in tr._map.keys()}
    if tr._key is not None:
        keys[tr._key.keyframe_id] = (tr._key.t_s, tr._key.p_W_m.copy())
    return keys


def main() -> int:
    ap = parser(__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=0)
    ap.add_argument("--list", action="store_true", help="one line per key change")
    ap.add_argument("--dump", type=Path, help="write the per-frame arrays to this .npz")
    args = ap.parse_args()
    params, seq, att = setup(args)
    tr = NislamTracker(seq.intrinsics, params)
    rows = []  # (result, keys before, keys after)
    for n, frame in enumerate(seq.frames()):
        if args.frames and n >= args.frames:
            break
        before = _keys(tr)
        r = tr.track(frame, att)
        tr.finish_frame()
        if r.trusted:
            rows.append((r, before, _keys(tr)))
    gt = seq.groundtruth
    t = np.array([r.t_s for r, _, _ in rows])
    ok = (t >= gt.t_s[0]) & (t <= gt.t_s[-1])
    rows = [x for x, keep in zip(rows, ok) if keep]
    t = t[ok]
    sl = Slerp(gt.t_s, Rotation.from_quat(gt.q_xyzw))

    def pos(ts):
        return np.stack([np.interp(ts, gt.t_s, gt.p_xyz_m[:, i]) for i in range(3)], axis=1)

    g0 = pos(np.array([rows[0][0].t_s]))[0] - rows[0][0].p_W_m  # tracker world = truth - g0
    est = np.array([r.p_W_m for r, _, _ in rows])
    true_p = pos(t) - g0
    err = est - true_p
    ref = np.array([r.reference_keyframe_id for r, _, _ in rows])
    reused = np.array([r.keyframe_reused for r, _, _ in rows])
    r_f = sl(t)
    step = r_f[:-1].inv().apply(np.diff(err, axis=0))
    n = np.linalg.norm(step, axis=1)
    same = ref[1:] == ref[:-1]
    chg = np.flatnonzero(~same) + 1
    key_err, meas_err, kinds = [], [], []
    lines = []
    for i in chg:
        r, before, after = rows[i]
        rp, _, _ = rows[i - 1]
        kold, knew = rp.reference_keyframe_id, r.reference_keyframe_id
        t_old, p_old = before.get(kold, after.get(kold))
        t_new, p_new = after[knew]
        e_old = p_old - (pos(np.array([t_old]))[0] - g0)
        e_new = p_new - (pos(np.array([t_new]))[0] - g0)
        de_key = r_f[i - 1].inv().apply(e_new - e_old)
        de_meas = step[i - 1] - de_key
        key_err.append(de_key)
        meas_err.append(de_meas)
        kind = "reuse" if reused[i] else "new"
        kinds.append(kind)
        lines.append(f"{i:4d} t={t[i] - t[0]:6.2f} {kind:5s} {kold:3d}->{knew:3d} jump {n[i - 1] * 1e3:5.1f} mm"
                     f" key {np.linalg.norm(de_key) * 1e3:5.1f} meas {np.linalg.norm(de_meas) * 1e3:5.1f}"
                     f" psr {r.psr:5.1f}/{rp.psr:5.1f} |e_key_new| {np.linalg.norm(e_new) * 1e3:5.1f}")
    key_err, meas_err, kinds = np.array(key_err), np.array(meas_err), np.array(kinds)
    if args.dump:
        kt = np.array([rows[i][2][r.reference_keyframe_id][0] for i, (r, _, _) in enumerate(rows)])
        kp = np.array([rows[i][2][r.reference_keyframe_id][1] for i, (r, _, _) in enumerate(rows)])
        meas = np.array([(-r.shift_cells[0] * r.res_m, -r.shift_cells[1] * r.res_m, r.tz_m)
                         for r, _, _ in rows])
        np.savez(args.dump, t=t, est=est, true_p=true_p, ref=ref, reused=reused,
                 psr=np.array([r.psr for r, _, _ in rows]), meas=meas, key_t=kt, key_p=kp,
                 inc_err=meas - sl(kt).inv().apply(true_p - (pos(kt) - g0)),
                 res=np.array([r.res_m for r, _, _ in rows]),
                 var=np.array([r.pose_var[:3] for r, _, _ in rows]))
    if args.list:
        print("\n".join(lines))
    m_ev = evaluate(Trajectory(t, est, np.array([r.q_W_C_xyzw for r, _, _ in rows])),
                    ground_truth_at(t, gt, 0.2)[0], reference_keyframe_id=ref)
    print(f"{len(rows)} frames; ATE {m_ev.ate_rmse_m * 1e3:.1f} mm; rpe1/3/10/30 "
          f"{m_ev.rpe_lag1_m * 1e3:.2f}/{m_ev.rpe_lag3_m * 1e3:.2f}/{m_ev.rpe_lag10_m * 1e3:.2f}/"
          f"{m_ev.rpe_lag30_m * 1e3:.2f} mm; path ratio {m_ev.path_length_ratio:.2f}")
    print(f"lag-1 {rms_mm(n):.2f} mm: same key {rms_mm(n[same]):.2f} x {same.sum()}, changes "
          f"{rms_mm(n[~same]):.2f} x {(~same).sum()} (share of squared error "
          f"{np.sum(n[~same] ** 2) / np.sum(n ** 2):.2f})")
    for kind in ("reuse", "new"):
        m = kinds == kind
        if not m.any():
            continue
        jn = n[chg[m] - 1]
        print(f"  {kind:5s} x {m.sum():2d}: jump {rms_mm(jn):.2f} RMS (median {np.median(jn) * 1e3:.2f}, max "
              f"{jn.max() * 1e3:.1f}); keys' own position {rms_mm(np.linalg.norm(key_err[m], axis=1)):.2f}, "
              f"measurement against the keys {rms_mm(np.linalg.norm(meas_err[m], axis=1)):.2f} mm RMS")
    kp = rows[-1][2]
    ke = np.array([p - (pos(np.array([tk]))[0] - g0) for tk, p in kp.values()])
    print(f"keys held at the end: {len(kp)}, position error {rms_mm(np.linalg.norm(ke, axis=1)):.1f} mm RMS")
    return 0


if __name__ == "__main__":
    sys.exit(main())
