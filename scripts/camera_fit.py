"""A recorded camera's fixed errors, fitted against its ground truth alone
(a script, not a test; no tracker runs; docs/nislam-error-budget.md, "What the
recorded camera's geometry says against its ground truth").

    python scripts/camera_fit.py SEQ_DIR depth  [--first A] [--last B]
    python scripts/camera_fit.py SEQ_DIR colour [--first A] [--last B]
    python scripts/camera_fit.py SEQ_DIR range  [--first A] [--last B] [--lag-ms X]

depth: frame i's depth pixels, moved by the ground-truth pose from i to j (at
the depths' instants), against frame j's depth where they land (pairs 3-15
frames apart, 2-35 deg). Fits a focal-length scale k (fx, fy times 1 + k), a
mount rotation m (R_W_C = R_W_C,gt exp(m)) and a depth correction
z_true = z (1 + c . (1, xn, yn, xn^2, yn^2, xn yn)), xn = (u - cx) / fx, by
robust least squares on residuals in units of the Kinect's noise.
colour: a world point from frame i's depth has one colour in frames i and j,
each colour row seen at its own time (the camera model's readout). Fits the
map from a depth pixel p to its colour pixel, c + s R(phi) (p - c) + d about
the principal point c, by the mean absolute gray difference (Nelder-Mead), on
the even and the odd pairs apart.
range: no fit; how far the depth agrees with itself against the ground truth,
by range. Frame i's depth pixels moved by the ground-truth pose to frame j and
compared with j's depth there (pairs 3-25 frames apart), the median residual
per range band and per rotation between the two views; then, per pair, the far
band's median residual in 1/z (the disparity domain, x f B for pixels) against
the rotation and the body rates at both frames (R^2 of a linear fit).
`--lag-ms` moves every depth instant (the camera model's lag plus this).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares, minimize
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sim_replay.tum import Sequence, open_sequence  # noqa: E402


def _pose_at(seq: Sequence, t_s) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth (R_W_C (M,3,3), p_W (M,3)) at `t_s` (Sequence.groundtruth_at:
    slerp and linear, never extrapolated); NaN where there is none."""
    p, q, valid = seq.groundtruth_at(np.atleast_1d(np.asarray(t_s, np.float64)))
    r = np.full((len(valid), 3, 3), np.nan)
    if valid.any():
        r[valid] = Rotation.from_quat(q[valid]).as_matrix()
    return r, p


def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """`img` at (u, v); -1 outside."""
    return cv2.remap(img, u.astype(np.float32).reshape(1, -1), v.astype(np.float32).reshape(1, -1),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=-1).ravel()


def _grid(h: int, w: int, step_px: int) -> tuple[np.ndarray, np.ndarray]:
    """(v, u) of every `step_px`-th pixel, flat."""
    vv, uu = np.mgrid[step_px // 2:h:step_px, step_px // 2:w:step_px]
    return vv.ravel().astype(np.float64), uu.ravel().astype(np.float64)


def _phi(xn: np.ndarray, yn: np.ndarray) -> np.ndarray:
    return np.stack([np.ones_like(xn), xn, yn, xn * xn, yn * yn, xn * yn])


def fit_depth(seq: Sequence, frames: range, step_px: int = 12) -> None:
    K = seq.intrinsics
    depth, pose = {}, {}
    for i in sorted({i + lag for i in frames for lag in (0, 3, 6, 10, 15)} & set(range(len(seq)))):
        f = seq.read_frame(i)
        if f is None:
            continue
        r, p = _pose_at(seq, f.t_s if f.depth_t_s is None else f.depth_t_s)
        if np.isfinite(r).all():
            depth[i], pose[i] = f.depth_m, (r, p)
    h, w = next(iter(depth.values())).shape
    vv, uu = _grid(h, w, step_px)
    pairs = []
    for i in frames:
        for j in (i + 3, i + 6, i + 10, i + 15):
            if i not in depth or j not in depth:
                continue
            (r_i, p_i), (r_j, p_j) = pose[i], pose[j]
            r_ji = r_j[0].T @ r_i[0]
            angle_deg = np.degrees(np.linalg.norm(Rotation.from_matrix(r_ji).as_rotvec()))
            if not 2.0 <= angle_deg <= 35.0:
                continue
            z = depth[i][vv.astype(int), uu.astype(int)].astype(np.float64)
            s = (z > 0.4) & (z < 4.0)
            if s.sum() >= 50:
                pairs.append((j, uu[s], vv[s], z[s], r_ji, r_j[0].T @ (p_i[0] - p_j[0])))

    def residuals(x: np.ndarray, strict: bool = False) -> np.ndarray:
        k, m, c = x[0], Rotation.from_rotvec(x[1:4]).as_matrix(), x[4:10]
        fx, fy = K.fx * (1 + k), K.fy * (1 + k)
        out = []
        for j, u, v, z, r_ji, t_ji in pairs:
            zc = z * (1.0 + c @ _phi((u - K.cx) / K.fx, (v - K.cy) / K.fy))
            p_i = np.stack([(u - K.cx) / fx * zc, (v - K.cy) / fy * zc, zc])
            q = (m.T @ r_ji @ m) @ p_i + (m.T @ t_ji)[:, None]
            uj, vj = K.cx + fx * q[0] / q[2], K.cy + fy * q[1] / q[2]
            if not strict:  # the points were chosen once: the fit cannot drop any
                uj, vj = np.clip(uj, 0, w - 1.001), np.clip(vj, 0, h - 1.001)
            zj = _bilinear(depth[j], uj, vj)
            if strict:  # a missing or edge neighbour: not a point to fit
                u0, v0 = np.floor(uj), np.floor(vj)
                near = [_bilinear(depth[j], u0 + a, v0 + b) for a in (0, 1) for b in (0, 1)]
                lo, hi = np.min(near, 0), np.max(near, 0)
                zj = np.where((lo > 0) & (hi - lo < 0.02 * hi), zj, np.nan)
            zj = zj * (1.0 + c @ _phi((uj - K.cx) / K.fx, (vj - K.cy) / K.fy))
            out.append((zj - q[2]) / (0.002 + 0.003 * q[2] ** 2))
        return np.concatenate(out)

    x0 = np.zeros(10)
    r0 = residuals(x0, strict=True)
    keep = np.isfinite(r0) & (np.abs(r0) < 6.0)  # occlusions and edges out, once
    res = least_squares(lambda x: residuals(x)[keep], x0, loss="soft_l1", f_scale=3.0,
                        x_scale=0.01)
    rms0, rms1 = np.sqrt(np.mean(r0[keep] ** 2)), np.sqrt(np.mean(res.fun ** 2))
    print(f"{len(pairs)} pairs, {keep.sum()} points; residual RMS {rms0:.3f} -> {rms1:.3f} "
          "(units of the depth noise)")
    print(f"focal scale {res.x[0]:+.4f}; mount {np.round(np.degrees(res.x[1:4]), 3)} deg; "
          f"depth c (1, xn, yn, xn^2, yn^2, xn yn) {np.round(res.x[4:], 4)}")


RANGE_BANDS_M = ((0.3, 1.0), (1.0, 1.5), (1.5, 2.0), (2.0, 2.5), (2.5, 3.0), (3.0, 4.0))
FAR_M = (2.5, 4.0)


def _body_rate_deg_s(seq: Sequence, t_s: float, half_s: float = 0.02) -> np.ndarray:
    """The ground truth's body rate at `t_s` (deg/s, camera axes), over +-half_s;
    NaN where the ground truth does not cover both ends."""
    r, _ = _pose_at(seq, [t_s - half_s, t_s + half_s])
    if not np.isfinite(r).all():
        return np.full(3, np.nan)
    return np.degrees(Rotation.from_matrix(r[0].T @ r[1]).as_rotvec()) / (2 * half_s)


def _r2(y: np.ndarray, x: np.ndarray) -> float:
    """R^2 of the least-squares line (plane) of y on the columns of x."""
    a = np.c_[np.ones(len(y)), x]
    e = y - a @ np.linalg.lstsq(a, y, rcond=None)[0]
    return float(1.0 - e.var() / y.var())


def depth_by_range(seq: Sequence, frames: range, lag_s: float = 0.0, step_px: int = 4) -> None:
    """The `range` report (module doc), over pairs starting at `frames`."""
    K = seq.intrinsics
    h, w = seq.camera.height, seq.camera.width
    vv, uu = _grid(h, w, step_px)
    views: dict[int, tuple | None] = {}

    def view(i: int) -> tuple | None:
        """(depth, its instant, R_W_C, p_W) of frame i; None: no frame or no pose."""
        if i not in views:
            f = seq.read_frame(i)
            views[i] = None
            if f is not None:
                t = (f.t_s if f.depth_t_s is None else f.depth_t_s) + lag_s
                r, p = _pose_at(seq, t)
                if np.isfinite(r).all():
                    views[i] = (f.depth_m, t, r[0], p[0])
        return views[i]

    rows, res, ranges, angles = [], [], [], []
    for i in frames:
        for j in (i + 3, i + 6, i + 10, i + 15, i + 25):
            if j >= len(seq) or view(i) is None or view(j) is None:
                continue
            (d_i, t_i, r_i, p_i), (d_j, t_j, r_j, p_j) = view(i), view(j)
            z = d_i[vv.astype(int), uu.astype(int)].astype(np.float64)
            s = z > 0.3
            x = np.stack([(uu[s] - K.cx) / K.fx * z[s], (vv[s] - K.cy) / K.fy * z[s], z[s]])
            q = r_j.T @ (r_i @ x + (p_i - p_j)[:, None])
            u_j = np.round(K.cx + K.fx * q[0] / q[2]).astype(int)
            v_j = np.round(K.cy + K.fy * q[1] / q[2]).astype(int)
            ok = (q[2] > 0.3) & (u_j >= 0) & (u_j < w) & (v_j >= 0) & (v_j < h)
            seen = np.zeros(len(ok))
            seen[ok] = d_j[v_j[ok], u_j[ok]]
            ok &= (seen > 0.3) & (np.abs(seen - q[2]) < 0.3 * q[2])  # the same surface
            angle = np.degrees(np.linalg.norm(Rotation.from_matrix(r_i.T @ r_j).as_rotvec()))
            res.append(seen[ok] - q[2][ok])
            ranges.append(q[2][ok])
            angles.append(np.full(int(ok.sum()), angle))
            far = ok & (q[2] >= FAR_M[0]) & (q[2] < FAR_M[1])
            if far.sum() >= 200:
                rows.append([np.median(1.0 / q[2][far] - 1.0 / seen[far]), angle,
                             *_body_rate_deg_s(seq, t_i), *_body_rate_deg_s(seq, t_j)])
    if not res:
        print("no pair of frames with depth and ground truth")
        return
    res, ranges, angles = np.concatenate(res), np.concatenate(ranges), np.concatenate(angles)
    print(f"depth instants moved by {lag_s * 1e3:+.0f} ms; median residual (measured - "
          "predicted from the other view, mm) and count per range band:")
    for lo, hi in ((0, 10), (10, 20), (20, 40)):
        sel = (angles >= lo) & (angles < hi)
        cells = []
        for z0, z1 in RANGE_BANDS_M:
            b = sel & (ranges >= z0) & (ranges < z1)
            med_mm = np.median(res[b]) * 1e3 if b.any() else np.nan
            cells.append(f"{z0:.1f}-{z1:.1f} m {med_mm:+6.1f} ({int(b.sum())})")
        print(f"  views {lo}-{hi} deg apart: " + " | ".join(cells))
    a = np.array(rows).reshape(-1, 8)
    a = a[np.isfinite(a).all(axis=1)]
    if len(a) < 10:
        print(f"{len(a)} pairs with far content ({FAR_M[0]}-{FAR_M[1]} m): too few to regress")
        return
    y = a[:, 0]
    print(f"{len(a)} pairs with far content ({FAR_M[0]}-{FAR_M[1]} m): median 1/z residual "
          f"{np.median(y):+.4f} 1/m, RMS {np.sqrt(np.mean(y ** 2)):.4f} 1/m (x f B for pixels)")
    print(f"  R^2 on the rotation between the views {_r2(y, a[:, 1:2]):.2f}; on the body rates at "
          f"both frames {_r2(y, a[:, 2:8]):.2f}; on their difference "
          f"{_r2(y, a[:, 5:8] - a[:, 2:5]):.2f}")


def fit_colour(seq: Sequence, frames: range, step_px: int = 8) -> None:
    K, readout_s = seq.intrinsics, seq.camera.readout_s
    gray, depth, t_colour, t_depth = {}, {}, {}, {}
    for i in sorted({i + lag for i in frames for lag in (0, 4, 8, 12)} & set(range(len(seq)))):
        f = seq.read_frame(i)
        if f is not None:
            g = cv2.cvtColor(f.bgr, cv2.COLOR_BGR2GRAY).astype(np.float32)
            gray[i], depth[i] = cv2.GaussianBlur(g, (0, 0), 1.5), f.depth_m
            t_colour[i], t_depth[i] = f.t_s, f.t_s if f.depth_t_s is None else f.depth_t_s
    h, w = next(iter(gray.values())).shape

    def colour_px(x_w: np.ndarray, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r, p = _pose_at(seq, np.full(len(x_w), t_colour[i]))
        for _ in range(2):  # the row's own time
            x_c = np.einsum("nji,nj->ni", r, x_w - p)
            u, v = K.cx + K.fx * x_c[:, 0] / x_c[:, 2], K.cy + K.fy * x_c[:, 1] / x_c[:, 2]
            r, p = _pose_at(seq, t_colour[i] + readout_s * (np.clip(v, 0, h) / h - 0.5))
        return u, v, x_c[:, 2]

    vv, uu = _grid(h, w, step_px)
    pairs = []
    for i in frames:
        if i not in gray:
            continue
        z = depth[i][vv.astype(int), uu.astype(int)].astype(np.float64)
        s = (z > 0.4) & (z < 3.5)
        r_d, p_d = _pose_at(seq, t_depth[i])
        if not np.isfinite(r_d).all():
            continue
        x_c = np.stack([(uu[s] - K.cx) / K.fx * z[s], (vv[s] - K.cy) / K.fy * z[s], z[s]], -1)
        x_w = x_c @ r_d[0].T + p_d[0]
        u_i, v_i, _ = colour_px(x_w, i)
        for j in (i + 4, i + 8, i + 12):
            if j not in gray:
                continue
            u_j, v_j, z_j = colour_px(x_w, j)
            ok = (np.isfinite(u_i) & (z_j > 0.3) & (u_j > 20) & (u_j < w - 20) & (v_j > 20)
                  & (v_j < h - 20))
            seen = depth[j][np.clip(v_j, 0, h - 1).astype(int), np.clip(u_j, 0, w - 1).astype(int)]
            ok &= np.abs(seen - z_j) < 0.03 * z_j  # not occluded in j
            if ok.sum() >= 50:
                pairs.append((i, j, u_i[ok], v_i[ok], u_j[ok], v_j[ok]))

    def cost(x: np.ndarray, sel: list) -> float:
        dx, dy, phi_deg, scale_pct = x
        turn = Rotation.from_euler("z", phi_deg, degrees=True).as_matrix()[:2, :2]
        a = (1 + scale_pct / 100) * turn

        def to_colour(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            uv = a @ np.stack([u - K.cx, v - K.cy])
            return K.cx + uv[0] + dx, K.cy + uv[1] + dy

        total, n = 0.0, 0
        for i, j, u_i, v_i, u_j, v_j in sel:
            g_i = _bilinear(gray[i], *to_colour(u_i, v_i))
            g_j = _bilinear(gray[j], *to_colour(u_j, v_j))
            ok = (g_i >= 0) & (g_j >= 0)
            d = g_i[ok] - g_j[ok]
            total += np.abs(d - np.median(d)).sum()  # the exposure's change between the two
            n += int(ok.sum())
        return total / n

    print(f"{len(pairs)} pairs, {sum(len(p[2]) for p in pairs)} points; mean |gray "
          f"difference| with the colour on the depth's grid {cost(np.zeros(4), pairs):.3f}")
    for name, sel in (("even pairs", pairs[::2]), ("odd pairs", pairs[1::2])):
        x0 = np.zeros(4)
        simplex = np.vstack([x0, x0 + np.diag([3.0, 3.0, 0.5, 1.0])])
        r = minimize(cost, x0, args=(sel,), method="Nelder-Mead", options={
            "xatol": 0.05, "fatol": 1e-4, "maxfev": 400, "initial_simplex": simplex})
        print(f"{name}: colour pixel = c + s R(phi) (p - c) + d, d ({r.x[0]:+.2f}, "
              f"{r.x[1]:+.2f}) px, phi {r.x[2]:+.3f} deg, s - 1 {r.x[3]:+.2f} %; "
              f"mean |gray difference| {r.fun:.3f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("seq")
    ap.add_argument("what", choices=("depth", "colour", "range"))
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--last", type=int, default=None, help="last frame a pair starts at")
    ap.add_argument("--lag-ms", type=float, default=0.0, help="range: move the depth instants")
    a = ap.parse_args()
    seq = open_sequence(a.seq)
    if seq.groundtruth is None:
        print(f"{a.seq}: no groundtruth.txt to fit against", file=sys.stderr)
        return 2
    last = len(seq) - 1 if a.last is None else min(a.last, len(seq) - 1)
    if a.what == "depth":
        fit_depth(seq, range(a.first, last + 1, 6))
    elif a.what == "range":
        depth_by_range(seq, range(a.first, last + 1, 4), a.lag_ms * 1e-3)
    else:
        fit_colour(seq, range(a.first, last + 1, 4))
    return 0


if __name__ == "__main__":
    sys.exit(main())
