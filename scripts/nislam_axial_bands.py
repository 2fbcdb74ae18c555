"""Where along the flight NI-SLAM's axial (t_z, Eq. 18) per-frame error sits: split by the matched cells' mean depth.

    .venv/bin/python scripts/nislam_axial_bands.py SEQ_DIR [--set KEY=VALUE ...] [--noise-deg X]

Replays SEQ_DIR with NI-SLAM and, for consecutive frames matched against the
same key, prints the lag-1 error of t_z against the true motion along the
key's axis (the budget's `ax`) per band of the matched cells' mean key depth:
pairs, RMS, share of the squared error, and the median of the matched cells,
of the key's and the frame's filled share of the overlap, and of the cells
filled in both (Eq. 18 compares a frame's cell with the same key cell only).
docs/nislam-error-budget.md, "Far views".
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from nislam_experiment import parser, rms_mm, setup  # noqa: E402

import onboard.nislam.tracker as tracker_mod  # noqa: E402
from onboard.nislam.calibration import overlap  # noqa: E402

BANDS_M = (0.0, 2.0, 3.0, 4.0, 100.0)


def main() -> int:
    args = parser(__doc__.split("\n\n")[0]).parse_args()
    params, seq, att = setup(args)
    calls = []
    original = tracker_mod.depth_translation

    def depth_translation(key, img, du, dv, p, frac=(0.0, 0.0)):
        fit = original(key, img, du, dv, p, frac)
        ks, cs = overlap(img.mask.shape, du, dv)
        km, cm = key.mask0[ks] > 0, img.mask[cs] > 0
        calls.append((key, fit, km.mean(), cm.mean(), (km & cm).mean()))
        return fit

    tracker_mod.depth_translation = depth_translation
    tr = tracker_mod.NislamTracker(seq.intrinsics, params)
    gt = seq.groundtruth
    rows = []
    for frame in seq.frames():
        calls.clear()
        r = tr.track(frame, att)
        hit = [c for c in calls if c[0].keyframe_id == r.reference_keyframe_id and c[1] is not None]
        if not (r.trusted and hit):
            continue
        key, fit, kf, cf, both = hit[-1]
        pk, qk, okk = gt.interpolate([key.t_s], 0.2)
        pf, _, okf = gt.interpolate([r.t_s], 0.2)
        if okk[0] and okf[0]:
            tz_true = Rotation.from_quat(qk[0]).inv().apply(pf[0] - pk[0])[2]
            rows.append((key.keyframe_id, fit.tz_m - tz_true, fit.z_mean_m, fit.matched, kf, cf, both))
    a = np.array(rows)
    same = a[1:, 0] == a[:-1, 0]
    de = np.diff(a[:, 1])[same]
    b = a[1:][same]
    print(f"{len(a)} frames, {same.sum()} same-key pairs, axial lag-1 {rms_mm(de):.2f} mm")
    print("| key depth m | pairs | ax lag-1 mm | share | matched cells | key filled | frame filled | both |")
    print("|---|---|---|---|---|---|---|---|")
    for lo, hi in zip(BANDS_M[:-1], BANDS_M[1:]):
        s = (b[:, 2] >= lo) & (b[:, 2] < hi)
        if s.any():
            print(f"| {lo:g}-{hi:g} | {s.sum()} | {rms_mm(de[s]):.2f} | {np.sum(de[s] ** 2) / np.sum(de ** 2):.2f} | "
                  f"{np.median(b[s, 3]):.0f} | {np.median(b[s, 4]):.2f} | {np.median(b[s, 5]):.2f} | {np.median(b[s, 6]):.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
