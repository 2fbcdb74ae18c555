"""Compiled inner loops of the FastORB tracker (numba), as onboard/nislam/kernels.py
is for NI-SLAM: each replaces a chain of small numpy passes whose call
overhead and temporaries cost more than the arithmetic on a few hundred
points. The numpy forms they replace stay the reference in the tests
(fastorb_pose._residuals, ...).

  pose_normal_equations  the refinement's Gauss-Newton system in one pass
                         (was (N, 3, 6) Jacobians, weights and two products)
  pose_residual_norms    residual norms for the inlier gates
  gms_keep               the grid motion statistic (was nine gathers per grid)
  radius_pairs           keypoint / projection pairs within a radius and
                         their Hamming distances (was a k-d tree per call)
  one_to_one             greedy one-to-one matches by a counting sort
  depth_at               sub-pixel depth with the edge test (16 gathers)

Compiled code is cached on disk (`cache=True`), and `warm_up()` compiles or
loads everything when a tracker is built, so no frame pays for compilation.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from numba import njit

log = logging.getLogger(__name__)


@njit(cache=True, nogil=True)
def _point_rows(R, t, X, u, v, d, fx, fy, cx, cy, bf, res, J):
    """Residual (3,) of one point into `res`, its Jacobian rows (3, 6) into
    `J` (left perturbation (phi, rho), as fastorb_pose._residuals); returns
    whether the disparity row is in use."""
    px = R[0, 0] * X[0] + R[0, 1] * X[1] + R[0, 2] * X[2] + t[0]
    py = R[1, 0] * X[0] + R[1, 1] * X[1] + R[1, 2] * X[2] + t[1]
    pz = R[2, 0] * X[0] + R[2, 1] * X[1] + R[2, 2] * X[2] + t[2]
    iz = 1.0 / max(pz, 1e-6)
    xz = px * iz
    yz = py * iz
    res[0] = fx * xz + cx - u
    res[1] = fy * yz + cy - v
    res[2] = 0.0
    J[0, 0] = -fx * xz * yz
    J[0, 1] = fx * (1.0 + xz * xz)
    J[0, 2] = -fx * yz
    J[0, 3] = fx * iz
    J[0, 4] = 0.0
    J[0, 5] = -fx * xz * iz
    J[1, 0] = -fy * (1.0 + yz * yz)
    J[1, 1] = fy * xz * yz
    J[1, 2] = fy * xz
    J[1, 3] = 0.0
    J[1, 4] = fy * iz
    J[1, 5] = -fy * yz * iz
    for k in range(6):
        J[2, k] = 0.0
    if bf > 0.0 and d > 0.0:
        res[2] = bf * iz - d
        g = -bf * iz * iz
        J[2, 0] = g * py
        J[2, 1] = -g * px
        J[2, 5] = g
        return True
    return False


@njit(cache=True, nogil=True)
def pose_normal_equations(R, t, obj, img, disp, sel, fx, fy, cx, cy, bf, huber):
    """Gauss-Newton system of the robust refinement over the points with
    `sel`: H = sum w J^T J (6, 6), g = sum w J^T r (6,), with Huber weights
    w on the residual norm (1 inside `huber`, huber / |r| beyond; all 1 when
    huber <= 0). Also returns (sum w |r|^2, sum of squared pixel residuals,
    number of observations: 2 per point plus 1 per disparity row, points)."""
    H = np.zeros((6, 6))
    g = np.zeros(6)
    res = np.zeros(3)
    J = np.zeros((3, 6))
    sse_w = 0.0
    sse_px = 0.0
    n_obs = 0
    n = 0
    for i in range(len(obj)):
        if not sel[i]:
            continue
        has = _point_rows(R, t, obj[i], img[i, 0], img[i, 1], disp[i], fx, fy, cx, cy, bf, res, J)
        r2 = res[0] * res[0] + res[1] * res[1] + res[2] * res[2]
        w = 1.0
        if huber > 0.0:
            r = np.sqrt(r2)
            if r > huber:
                w = huber / max(r, 1e-12)
        rows = 3 if has else 2
        for a in range(6):
            acc = 0.0
            for k in range(rows):
                acc += J[k, a] * res[k]
            g[a] += w * acc
            for b in range(a, 6):
                acc = 0.0
                for k in range(rows):
                    acc += J[k, a] * J[k, b]
                H[a, b] += w * acc
        sse_w += w * r2
        sse_px += res[0] * res[0] + res[1] * res[1]
        n_obs += rows
        n += 1
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g, sse_w, sse_px, n_obs, n


@njit(cache=True, nogil=True)
def pose_residual_norms(R, t, obj, img, disp, fx, fy, cx, cy, bf):
    """|residual| (N,) [px] of every point: reprojection and, where a
    disparity was measured, the disparity residual."""
    out = np.empty(len(obj))
    for i in range(len(obj)):
        X = obj[i]
        px = R[0, 0] * X[0] + R[0, 1] * X[1] + R[0, 2] * X[2] + t[0]
        py = R[1, 0] * X[0] + R[1, 1] * X[1] + R[1, 2] * X[2] + t[1]
        pz = R[2, 0] * X[0] + R[2, 1] * X[1] + R[2, 2] * X[2] + t[2]
        iz = 1.0 / max(pz, 1e-6)
        ru = fx * px * iz + cx - img[i, 0]
        rv = fy * py * iz + cy - img[i, 1]
        r2 = ru * ru + rv * rv
        if bf > 0.0 and disp[i] > 0.0:
            rd = bf * iz - disp[i]
            r2 += rd * rd
        out[i] = np.sqrt(r2)
    return out


@njit(cache=True, nogil=True)
def gms_keep(left_x, left_y, right_cell, cols, rows, n_right, alpha):
    """The counting of fastorb_match.gms_inliers (see there), which bins the
    points: `left_x` / `left_y` (2, N) the 1-based left-grid cells without
    and with the half-cell shift, `right_cell` (N,) the flat cell in the
    padded right grid (row length cols + 2) of `n_right` cells. For each
    match the support of its own cell pair over the 3 x 3 neighbourhood,
    under the four placements; kept when one placement's support exceeds
    alpha sqrt(mean matches per neighbouring cell)."""
    n = len(right_cell)
    keep = np.zeros(n, np.bool_)
    rw = cols + 2
    for shift in range(4):
        sx, sy = shift & 1, (shift >> 1) & 1
        lc, lr = cols + sx, rows + sy
        lw = lc + 2
        pairs = np.zeros(((lr + 2) * lw, n_right), np.int32)
        per_cell = np.zeros((lr + 2) * lw, np.int64)
        for i in range(n):
            c = left_y[sy, i] * lw + left_x[sx, i]
            pairs[c, right_cell[i]] += 1
            per_cell[c] += 1
        for i in range(n):
            if keep[i]:
                continue
            ax, ay = left_x[sx, i], left_y[sy, i]
            c = ay * lw + ax
            support = 0
            total = 0
            cells = 0
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    support += pairs[c + dy * lw + dx, right_cell[i] + dy * rw + dx]
                    total += per_cell[c + dy * lw + dx]
                    if 1 <= ay + dy <= lr and 1 <= ax + dx <= lc:
                        cells += 1
            if support > alpha * np.sqrt(total / max(cells, 1)):
                keep[i] = True
    return keep


@njit(cache=True, nogil=True)
def _popcount64(x):
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (x * np.uint64(0x0101010101010101)) >> np.uint64(56)


@njit(cache=True, nogil=True)
def radius_pairs(kp_uv, map_uv, radius_px, desc64, map_desc64, max_hamming, w, h):
    """(keypoint, map point, Hamming distance) for every pair within
    `radius_px` (Euclidean) whose descriptors differ by at most `max_hamming`
    bits, in map-point order, keypoints ascending. Keypoints are binned in
    cells of the radius, so each map point looks at 3 x 3 cells. Descriptors
    as (N, 4) uint64."""
    cell = max(radius_px, 1.0)
    gc = int(w / cell) + 1
    gr = int(h / cell) + 1
    n = len(kp_uv)
    bins = np.empty(n, np.int64)
    counts = np.zeros(gc * gr + 1, np.int64)
    for i in range(n):
        x = min(max(int(kp_uv[i, 0] / cell), 0), gc - 1)
        y = min(max(int(kp_uv[i, 1] / cell), 0), gr - 1)
        bins[i] = y * gc + x
        counts[bins[i] + 1] += 1
    for b in range(gc * gr):
        counts[b + 1] += counts[b]
    order = np.empty(n, np.int64)
    fill = counts[:-1].copy()
    for i in range(n):  # stable: keypoints ascending within a cell
        order[fill[bins[i]]] = i
        fill[bins[i]] += 1
    r2 = radius_px * radius_px
    cap = 64
    q = np.empty(cap, np.int64)
    t = np.empty(cap, np.int64)
    d = np.empty(cap, np.int64)
    m = 0
    cand = np.empty(n, np.int64)
    for j in range(len(map_uv)):
        mu, mv = map_uv[j, 0], map_uv[j, 1]
        x0 = min(max(int(mu / cell), 0), gc - 1)
        y0 = min(max(int(mv / cell), 0), gr - 1)
        nc = 0
        for y in range(max(y0 - 1, 0), min(y0 + 2, gr)):
            for x in range(max(x0 - 1, 0), min(x0 + 2, gc)):
                b = y * gc + x
                for k in range(counts[b], counts[b + 1]):
                    i = order[k]
                    du = kp_uv[i, 0] - mu
                    dv = kp_uv[i, 1] - mv
                    if du * du + dv * dv <= r2:  # insert in order: a handful each
                        c = nc
                        while c > 0 and cand[c - 1] > i:
                            cand[c] = cand[c - 1]
                            c -= 1
                        cand[c] = i
                        nc += 1
        for c in range(nc):
            i = cand[c]
            dist = 0
            for word in range(desc64.shape[1]):
                dist += int(_popcount64(desc64[i, word] ^ map_desc64[j, word]))
            if dist > max_hamming:
                continue
            if m == cap:
                cap *= 2
                q2, t2, d2 = np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap, np.int64)
                q2[:m], t2[:m], d2[:m] = q, t, d
                q, t, d = q2, t2, d2
            q[m], t[m], d[m] = i, j, dist
            m += 1
    return q[:m], t[:m], d[:m]


@njit(cache=True, nogil=True)
def one_to_one(q, t, d, n_q, n_t):
    """fastorb_match._unique_pairs for small integer distances: pairs in
    order of increasing distance `d` (>= 0; stable), the first for each
    keypoint `q` (< n_q), then of those the first for each map point `t`
    (< n_t). Returns their indices into the input, best first."""
    n = len(d)
    top = 0
    for k in range(n):
        top = max(top, d[k])
    start = np.zeros(top + 2, np.int64)
    for k in range(n):
        start[d[k] + 1] += 1
    for v in range(top + 1):
        start[v + 1] += start[v]
    order = np.empty(n, np.int64)
    for k in range(n):  # counting sort: stable
        order[start[d[k]]] = k
        start[d[k]] += 1
    seen_q = np.zeros(n_q, np.bool_)
    seen_t = np.zeros(n_t, np.bool_)
    out = np.empty(n, np.int64)
    m = 0
    for k in order:
        if seen_q[q[k]]:
            continue
        seen_q[q[k]] = True
        if seen_t[t[k]]:
            continue
        seen_t[t[k]] = True
        out[m] = k
        m += 1
    return out[:m]


@njit(cache=True, nogil=True)
def depth_at(depth_m, uv, min_depth_m, max_depth_m, edge_rel):
    """fastorb_map.sample_depth (see there), one point at a time."""
    h, w = depth_m.shape
    out = np.zeros(len(uv))
    for i in range(len(uv)):
        x = min(max(uv[i, 0], 1.0), w - 3.0)
        y = min(max(uv[i, 1], 1.0), h - 3.0)
        u0 = int(np.floor(x))
        v0 = int(np.floor(y))
        fx = x - u0
        fy = y - v0
        lo = np.inf
        hi = -np.inf
        for dv in range(-1, 3):
            for du in range(-1, 3):
                z = np.float64(depth_m[v0 + dv, u0 + du])
                lo = min(lo, z)
                hi = max(hi, z)
        z00 = np.float64(depth_m[v0, u0])
        z01 = np.float64(depth_m[v0, u0 + 1])
        z10 = np.float64(depth_m[v0 + 1, u0])
        z11 = np.float64(depth_m[v0 + 1, u0 + 1])
        z = (z00 * (1 - fx) + z01 * fx) * (1 - fy) + (z10 * (1 - fx) + z11 * fx) * fy
        if z > min_depth_m and z < max_depth_m and lo > 0 and hi - lo <= edge_rel * z:
            out[i] = z
    return out


def warm_up() -> None:
    """Compile (or load from the disk cache) every kernel for the argument
    types the tracker passes."""
    t0 = time.perf_counter()
    R, v3 = np.eye(3), np.zeros(3)
    obj, img, disp = np.ones((2, 3)), np.zeros((2, 2)), np.zeros(2)
    pose_normal_equations(R, v3, obj, img, disp, np.ones(2, np.bool_), 1.0, 1.0, 0.0, 0.0,
                          1.0, 1.0)
    pose_residual_norms(R, v3, obj, img, disp, 1.0, 1.0, 0.0, 0.0, 1.0)
    cells = np.ones((2, 2), np.int64)
    gms_keep(cells, cells, cells[0] + 18, 16, 12, 14 * 18, 6.0)
    d64 = np.zeros((2, 4), np.uint64)
    q, t, d = radius_pairs(img, img, 15.0, d64, d64, 64, 640.0, 480.0)
    one_to_one(q, t, d, 2, 2)
    depth_at(np.zeros((8, 8), np.float32), img, 0.2, 6.0, 0.05)
    depth_at(np.zeros((8, 8), np.float32), img.astype(np.float32), 0.2, 6.0, 0.05)  # LK's pixels
    log.debug("FastORB kernels ready in %.2f s", time.perf_counter() - t0)
