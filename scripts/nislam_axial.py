"""Where NI-SLAM's axial (t_z, Eq. 18) per-frame error comes from, on a flight with exact truth.

    .venv/bin/python scripts/nislam_axial.py SEQ_DIR [--set KEY=VALUE ...] [--noise-deg X] [--frames N]

Replays SEQ_DIR with NI-SLAM (its decisions unchanged) and, at every frame's
match against its reference key, re-computes t_z from the same key and
projection with one thing changed at a time: the shift it compares at (the
tracker's peak or the true one), the key's depth (refined, Eq. 19, or as
projected), the estimator (weighted / plain mean, median, carry on / off).
Each variant's error against the true motion along the key's axis, lag-1 over
frames matched against the same key (the budget's `ax`), and its RMS against
the key, are printed (docs/nislam-error-budget.md, "The axial part, split").
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from nislam_experiment import parser, rms_mm, setup  # noqa: E402

import onboard.nislam.tracker as tracker_mod  # noqa: E402


def slope_grid(depth, mask, axis):
    """kernels._slope on every cell at once (same rule), along `axis`."""
    d = depth.astype(float)
    m = mask > 0
    n = d.shape[axis]
    out = np.zeros_like(d)
    done = np.zeros(d.shape, bool)
    idx = np.arange(n).reshape((-1, 1) if axis == 0 else (1, -1))
    for k in (1, 2):
        def sh(a, off, fill):
            r = np.roll(a, -off, axis=axis)
            bad = (idx + off < 0) | (idx + off >= n)
            return np.where(bad, fill, r)
        lo_m, hi_m = sh(m, -k, False), sh(m, k, False)
        lo_d, hi_d = sh(d, -k, 0.0), sh(d, k, 0.0)
        both = lo_m & hi_m & ~done
        out[both] = (0.5 * (hi_d - lo_d) / k)[both]
        done |= both
        hi = hi_m & ~done
        out[hi] = ((hi_d - d) / k)[hi]
        done |= hi
        lo = lo_m & ~done
        out[lo] = ((d - lo_d) / k)[lo]
        done |= lo
    return out


_SLOPES: dict = {}


def _cells(kd, km, kg, cd, cm, cg, du, dv, p, step):
    """Per-cell arrays of Eq. 18 at the whole-cell shift (du, dv): the key
    and current depth, the key's slopes, over cells matched in gray."""
    h, w = kd.shape
    ky0, ky1 = max(0, -dv), min(h, h - dv)
    kx0, kx1 = max(0, -du), min(w, w - du)
    ks = (slice(ky0, ky1, step), slice(kx0, kx1, step))
    cs = (slice(ky0 + dv, ky1 + dv, step), slice(kx0 + du, kx1 + du, step))
    ok = (km[ks] > 0) & (cm[cs] > 0) & (np.abs(cg[cs] - kg[ks]) < p.gate_gray)
    ii, jj = np.nonzero(ok)
    ii = ii * step + ky0
    jj = jj * step + kx0
    sk = (id(kd), kd.ctypes.data, float(kd.sum()))
    if _SLOPES.get("key") != sk:
        _SLOPES.update(key=sk, gx=slope_grid(kd, km, 1), gy=slope_grid(kd, km, 0))
    gx = _SLOPES["gx"][ii, jj]
    gy = _SLOPES["gy"][ii, jj]
    return kd[ii, jj].astype(float), cd[ii + dv, jj + du].astype(float), gx, gy, ii, jj


def estimate(kd, km, kg, cd, cm, cg, u, v, p, how="weighted", step=2):
    """t_z at the sub-cell shift (u, v) by estimator `how`."""
    du, dv = int(round(u)), int(round(v))
    fu, fv = u - du, v - dv
    zk, zc, gx, gy, _, _ = _cells(kd, km, kg, cd, cm, cg, du, dv, p, step)
    if len(zk) < p.min_matched_cells:
        return np.nan
    d = zc - zk
    med = np.median(d)
    if how != "nocarry":
        d = d + fu * gx + fv * gy
    z = 0.5 * (zk + zc - med)
    sz = np.maximum(p.depth_sigma_rel * z * z, p.depth_sigma_floor_m)
    gate = p.gate_depth_m
    if how not in ("mean", "nocarry", "median"):  # the weighted fit's gate (depth_gate_sigmas)
        gate = np.maximum(gate, p.depth_gate_sigmas * np.sqrt(2.0) * sz)
    keep = np.abs(d - med) < gate
    d, zk, zc, gx, gy, sz = d[keep], zk[keep], zc[keep], gx[keep], gy[keep], sz[keep]
    if how in ("mean", "nocarry"):
        return -float(np.mean(d))
    if how == "median":
        return -float(np.median(d))
    var = sz * sz + (gx * gx + gy * gy) / 6.0
    if how == "noslope":  # inverse variance of the sensor noise only
        var = sz * sz
    if how == "flat":  # only cells whose key slope is under 2 mm per cell
        sel = np.hypot(gx, gy) < 0.002
        return -float(np.mean(d[sel])) if sel.sum() > 50 else np.nan
    wt = 1.0 / var
    tz = -float(np.sum(wt * d) / np.sum(wt))
    if how.startswith("gate"):  # re-gated at k sigma of each cell around the first estimate
        k = float(how[4:])
        sd = np.sqrt(2.0 * var)
        for _ in range(2):
            keep = np.abs(d + tz) < k * sd
            tz = -float(np.sum(wt[keep] * d[keep]) / np.sum(wt[keep]))
    if how == "huber":
        sd = np.sqrt(2.0 * var)
        for _ in range(3):
            r = np.abs(d + tz) / sd
            wh = wt * np.minimum(1.0, 1.345 / np.maximum(r, 1e-9))
            tz = -float(np.sum(wh * d) / np.sum(wh))
    return tz


VARIANTS = {
    "tracker (weighted, carry, peak)": ("peak", "ref", "weighted", 2),
    "true shift": ("true", "ref", "weighted", 2),
    "key refined (Eq. 19)": ("peak", "refined", "weighted", 2),
    "key refined, true shift": ("true", "refined", "weighted", 2),
    "plain mean, carry": ("peak", "ref", "mean", 2),
    "plain mean, carry, true shift": ("true", "ref", "mean", 2),
    "plain mean, no carry": ("peak", "ref", "nocarry", 2),
    "median": ("peak", "ref", "median", 2),
    "sensor-noise weights only": ("peak", "ref", "noslope", 2),
    "flat cells only (< 2 mm/cell)": ("peak", "ref", "flat", 2),
    "every cell (step 1)": ("peak", "ref", "weighted", 1),
    "re-gated at 3 sigma": ("peak", "ref", "gate3", 2),
    "re-gated at 2 sigma": ("peak", "ref", "gate2", 2),
    "huber": ("peak", "ref", "huber", 2),
    "re-gated at 3 sigma, true shift": ("true", "ref", "gate3", 2),
}


def main() -> int:
    ap = parser(__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--only", nargs="*", default=None, help="variant names (prefixes)")
    args = ap.parse_args()
    params, seq, att = setup(args)
    gt = seq.groundtruth
    variants = {k: v for k, v in VARIANTS.items()
                if args.only is None or any(k.startswith(o) for o in args.only)}
    calls = []
    original = tracker_mod.depth_translation

    def depth_translation(key, img, du, dv, p, frac=(0.0, 0.0)):
        fit = original(key, img, du, dv, p, frac)
        calls.append((key, img, du + frac[0], dv + frac[1], fit))
        return fit

    tracker_mod.depth_translation = depth_translation
    tr = tracker_mod.NislamTracker(seq.intrinsics, params)
    rows = []
    for k, frame in enumerate(seq.frames()):
        if args.frames is not None and k >= args.frames:
            break
        calls.clear()
        r = tr.track(frame, att)
        if not r.trusted:
            continue
        hit = [c for c in calls if c[0].keyframe_id == r.reference_keyframe_id and c[4] is not None]
        if not hit:
            continue
        key, img, u, v, fit = hit[-1]
        pk, qk, okk = gt.interpolate([key.t_s], 0.2)
        pf, _, okf = gt.interpolate([r.t_s], 0.2)
        if not (okk[0] and okf[0]):
            continue
        t_true = Rotation.from_quat(qk[0]).inv().apply(pf[0] - pk[0])
        s = key.img.res_m
        ut, vt = -t_true[0] / s, -t_true[1] / s
        est = {}
        for name, (shift, kdep, how, step) in variants.items():
            # "ref": what the tracker compares with (the key as projected, Key.match_depth)
            kd = key.match_depth if kdep == "ref" else key.depth_ref
            kg = key.match_gray if kdep == "ref" else key.gray_ref
            su, sv = (u, v) if shift == "peak" else (ut, vt)
            est[name] = estimate(kd, key.mask0, kg, img.depth_m, img.mask, img.gray,
                                 su, sv, params, how, step)
        rows.append((key.keyframe_id, t_true[2], fit.tz_m, est, (u - ut) * s, (v - vt) * s, s))
        del key, img
    kid = np.array([r[0] for r in rows])
    same = kid[1:] == kid[:-1]
    tz_true = np.array([r[1] for r in rows])
    print(f"{len(rows)} frames, {same.sum()} same-key pairs; tracker t_z check: "
          f"{rms_mm(np.array([r[2] for r in rows]) - np.array([r[3].get(next(iter(variants)), np.nan) for r in rows])):.3f} mm")
    lat = np.array([(r[4], r[5]) for r in rows])
    dl = np.diff(lat, axis=0)[same]
    print(f"lateral peak error against the key u / v: {rms_mm(lat[:, 0]):.2f} / {rms_mm(lat[:, 1]):.2f} mm, "
          f"lag-1 {rms_mm(dl[:, 0]):.2f} / {rms_mm(dl[:, 1]):.2f} mm")
    print("| t_z variant | ax lag-1 mm | against the key mm | median abs mm |\n|---|---|---|---|")
    for name in variants:
        e = np.array([r[3][name] for r in rows]) - tz_true
        de = np.diff(e)[same]
        de = de[np.isfinite(de)]
        ef = e[np.isfinite(e)]
        print(f"| {name} | {rms_mm(de):.2f} | {rms_mm(ef):.2f} | {np.median(np.abs(ef)) * 1e3:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
