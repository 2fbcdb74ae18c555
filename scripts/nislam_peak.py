"""Sub-cell peak estimators scored on the responses NI-SLAM computes on a sequence.

    .venv/bin/python scripts/nislam_peak.py SEQ_DIR [--set KEY=VALUE ...] [--noise-deg X] [--frames N]

Replays SEQ_DIR (TUM layout with ground truth) with NI-SLAM, keeps the
response around each trusted frame's peak, then re-reads the sub-cell peak
from the same responses with several estimators and prints, per estimator,
the same-key lateral lag-1 error (docs/nislam-error-budget.md, "The
correlation peak on tum_fr1_rpy"): the tracker's shift against the key,
(-du s, -dv s), against the true motion since the key's frame in the key's
true axes, differenced between consecutive frames matched against the same
key; and the RMS of the error against the key. Also the response's width at
the peak (from the log-curvature) and the size of the lobe above half height.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation, Slerp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from nislam_experiment import parser, setup  # noqa: E402

import onboard.nislam.tracker as tracker_mod  # noqa: E402
from onboard.nislam import correlation  # noqa: E402
from sim_replay.budget import KeyTimes  # noqa: E402

R = 12  # half window kept around each peak (cells), as correlation._LOBE_HALF_CELLS
YY, XX = np.mgrid[-R:R + 1, -R:R + 1]


def _log_parabola(w: np.ndarray) -> tuple[float, float]:
    off = correlation._parabolic_offset
    return off(w[R, R - 1], w[R, R], w[R, R + 1]), off(w[R - 1, R], w[R, R], w[R + 1, R])


def _centroid(w: np.ndarray, radius: float, connected: bool, power: int = 1) -> tuple[float, float]:
    above = w - 0.5 * w[R, R]
    region = (above > 0) & (XX**2 + YY**2 <= radius * radius)
    if connected:
        labels, _ = ndimage.label(region)
        region = labels == labels[R, R]
    wt = np.where(region, above, 0.0) ** power
    return float((wt * XX).sum() / wt.sum()), float((wt * YY).sum() / wt.sum())


def _quadratic_on_log(w: np.ndarray, half: int) -> tuple[float, float]:
    s = slice(R - half, R + half + 1)
    x, y = XX[s, s].ravel().astype(float), YY[s, s].ravel().astype(float)
    f = np.log(np.clip(w[s, s].ravel(), 1e-12 * w[R, R], None))
    c = np.linalg.lstsq(np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], 1), f, rcond=None)[0]
    hess = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
    if np.linalg.eigvalsh(hess).max() >= 0:
        return _log_parabola(w)
    d = np.linalg.solve(hess, -c[1:3])
    return (float(d[0]), float(d[1])) if np.abs(d).max() <= 1.5 else _log_parabola(w)


ESTIMATORS = {
    "log-parabola per axis": _log_parabola,
    "2-D quadratic on the log, 3x3": lambda w: _quadratic_on_log(w, 1),
    "2-D quadratic on the log, 5x5": lambda w: _quadratic_on_log(w, 2),
    "centroid above half, radius 6": lambda w: _centroid(w, 6, False),
    "centroid of the connected lobe (tracker)": lambda w: _centroid(w, 2 * R, True),
    "same, weights squared": lambda w: _centroid(w, 2 * R, True, 2),
}


def main() -> int:
    ap = parser(__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=0, help="stop after N frames (0: all)")
    args = ap.parse_args()
    params, seq, att = setup(args)
    calls: list = []
    find_peak = tracker_mod.find_peak

    def recording_find_peak(resp, *a, **k):
        pk = find_peak(resp, *a, **k)
        h, w = resp.shape
        # The arg-max cell: what both sub-cell readings start from.
        u, v = int(round(pk.du_cells)) % w, int(round(pk.dv_cells)) % h
        win = resp[np.ix_(np.arange(v - R, v + R + 1) % h, np.arange(u - R, u + R + 1) % w)]
        calls.append((pk, win.astype(np.float64)))
        return pk

    tracker_mod.find_peak = recording_find_peak
    tr = tracker_mod.NislamTracker(seq.intrinsics, params)
    rows, key_t = [], KeyTimes()
    for i, frame in enumerate(seq.frames()):
        if args.frames and i >= args.frames:
            break
        calls.clear()
        r = tr.track(frame, att)
        key_t.add(r)
        match = [w for pk, w in calls if (pk.du_cells, pk.dv_cells) == r.shift_cells]
        if r.trusted and match and np.isfinite(r.psr):
            rows.append((r.t_s, key_t.get(r.reference_keyframe_id, np.nan), r.reference_keyframe_id,
                         r.res_m, r.shift_cells, match[-1]))
    gt = seq.groundtruth
    t = np.array([x[0] for x in rows])
    kt = np.array([x[1] for x in rows])
    ok = np.isfinite(kt) & (t >= gt.t_s[0]) & (t <= gt.t_s[-1]) & (kt >= gt.t_s[0])
    rows = [x for x, keep in zip(rows, ok) if keep]
    t, kt = t[ok], kt[ok]
    kid = np.array([x[2] for x in rows])
    res = np.array([x[3] for x in rows])
    whole = np.round(np.array([x[4] for x in rows]))
    wins = [x[5] for x in rows]
    sl = Slerp(gt.t_s, Rotation.from_quat(gt.q_xyzw))

    def pos(ts):
        return np.stack([np.interp(ts, gt.t_s, gt.p_xyz_m[:, i]) for i in range(3)], axis=1)

    true_inc = sl(kt).inv().apply(pos(t) - pos(kt))[:, :2]
    same = np.flatnonzero(kid[1:] == kid[:-1]) + 1
    lg = np.log(np.clip(np.array(wins), 1e-9, None) / np.array([w[R, R] for w in wins])[:, None, None])
    curv = -(lg[:, R, R - 1] - 2 * lg[:, R, R] + lg[:, R, R + 1])
    lobe = [int((ndimage.label(w > 0.5 * w[R, R])[0] == ndimage.label(w > 0.5 * w[R, R])[0][R, R]).sum())
            for w in wins]
    print(f"{len(rows)} frames, {len(same)} same-key pairs; cells {np.median(res) * 1e3:.1f} mm (median); "
          f"width at the peak {np.median(1 / np.sqrt(np.clip(curv, 1e-6, None))):.2f} cells; "
          f"lobe above half height {np.median(lobe):.0f} cells (median), {np.max(lobe)} max")
    print("| estimator | same-key lateral lag-1 mm | against the key mm |\n|---|---|---|")
    for name, est in ESTIMATORS.items():
        sub = np.array([est(w) for w in wins])
        err = -(whole + sub) * res[:, None] - true_inc
        step = err[same] - err[same - 1]
        print(f"| {name} | {np.sqrt(np.mean(np.sum(step**2, 1))) * 1e3:.2f} | "
              f"{np.sqrt(np.mean(np.sum(err**2, 1))) * 1e3:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
