"""Compiled inner loops of the NI-SLAM tracker (numba).

Each replaces a chain of numpy passes whose temporaries cost more than the
arithmetic: the z-buffer projection (Sec. IV-A) went from ~5 ms to ~1 ms per
frame, the depth-difference statistics (Eq. 18 and the tilt fit) from ~2 ms
to a single pass, and so did the block means of the residual-rotation fit;
the correlation filter's own passes are in filter_kernels.py.

Compiled code is cached on disk (`cache=True`: next to this file, or in
NUMBA_CACHE_DIR, which the systemd unit points at its cache directory), and
`warm_up()` compiles or loads everything before the first frame, so no frame
pays for compilation.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from numba import njit

from onboard.nislam import filter_kernels

log = logging.getLogger(__name__)

_EMPTY = np.uint32(0xFFFFFFFF)
DEPTH_UNITS_PER_M = 1.0e4  # z-buffer code: 24 bits of 0.1 mm depth above 8 bits of gray
_DEPTH_CODE_MAX = 16777215.0


@njit(cache=True, nogil=True)
def zbuffer_project(
    depth_m: np.ndarray,
    gray8: np.ndarray,
    rays: np.ndarray,
    m: np.ndarray,
    h: int,
    w: int,
    want_winner: bool,
    front_m: float = 0.0,
    front_rel: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Orthographic z-buffer projection of an organised cloud.

    Point (i, j) is rays[i, j] * depth_m[i, j]; its grid coordinates are the
    affine map m (3 x 4): (u, v) = m[:2] @ (p, 1) in cells, z' = m[2, :3] @ p.
    Cell (v, u) = (floor v, floor u) inside the grid; the nearest point wins
    and brings its gray (depth and gray packed in one integer, so one compare
    decides). Returns depth [m], gray in [0, 1], 0/1 mask (all (h, w) float32,
    holes 0) and, with want_winner, the flat pixel index that won each cell
    (-1 for holes) so key frames can pick up colour.

    front_m > 0: a cell's depth is the mean of the points on its front
    surface (within front_m + front_rel z^2 of the nearest so far) instead
    of the nearest's: under depth noise the nearest of n points is biased
    toward the camera by sigma E[min of n normals] (-0.56 sigma for 2, -1.16
    sigma for 5), n follows the distance to the surface and differs between
    key and frame, and t_z (Eq. 18) took the difference.
    """
    n_cells = h * w
    zbuf = np.full(n_cells, _EMPTY, np.uint32)
    winner = np.full(n_cells if want_winner else 0, -1, np.int32)
    front = front_m > 0.0
    zmin = np.full(n_cells if front else 0, np.inf, np.float32)
    zsum = np.zeros(n_cells if front else 0, np.float32)
    zcnt = np.zeros(n_cells if front else 0, np.float32)
    rows, cols = depth_m.shape
    for i in range(rows):
        for j in range(cols):
            z = depth_m[i, j]
            if not z > 0.0:
                continue
            x = rays[i, j, 0] * z
            y = rays[i, j, 1] * z
            zr = m[2, 0] * x + m[2, 1] * y + m[2, 2] * z
            uf = m[0, 0] * x + m[0, 1] * y + m[0, 2] * z + m[0, 3]
            vf = m[1, 0] * x + m[1, 1] * y + m[1, 2] * z + m[1, 3]
            # Range-checked in floating point first: the int conversion is then
            # a floor, and NaN never reaches it.
            if not (zr > 0.0 and 0.0 <= uf < w and 0.0 <= vf < h):
                continue
            idx = int(vf) * w + int(uf)
            code = np.uint32(min(zr * DEPTH_UNITS_PER_M, _DEPTH_CODE_MAX))
            key = (code << np.uint32(8)) | np.uint32(gray8[i, j])
            if key < zbuf[idx]:
                zbuf[idx] = key
                if want_winner:
                    winner[idx] = i * cols + j
            if front:
                z0 = zmin[idx]
                margin = front_m + front_rel * z0 * z0 if z0 < np.inf else 0.0
                if zr < z0 - margin:  # a surface in front of what the cell held
                    zmin[idx] = zr
                    zsum[idx] = zr
                    zcnt[idx] = 1.0
                elif zr <= z0 + margin:  # the same front surface
                    zmin[idx] = min(z0, zr)
                    zsum[idx] += zr
                    zcnt[idx] += 1.0
    # One flat pass writing every cell (holes too): LLVM turns the branch into
    # selects and vectorises it, 0.05 ms against 0.37 ms for the 2-D loop
    # over zero-filled arrays (360 x 480 cells).
    depth = np.empty(n_cells, np.float32)
    gray = np.empty(n_cells, np.float32)
    mask = np.empty(n_cells, np.float32)
    to_m = np.float32(1.0 / DEPTH_UNITS_PER_M)
    to_unit = np.float32(1.0 / 255.0)
    for k in range(n_cells):
        c = zbuf[k]
        if c != _EMPTY:
            if front:
                depth[k] = zsum[k] / zcnt[k]
            else:
                depth[k] = np.float32(c >> np.uint32(8)) * to_m
            gray[k] = np.float32(c & np.uint32(255)) * to_unit
            mask[k] = 1.0
        else:
            depth[k] = 0.0
            gray[k] = 0.0
            mask[k] = 0.0
    return depth.reshape(h, w), gray.reshape(h, w), mask.reshape(h, w), winner


@njit(cache=True, nogil=True)
def strided_depth_gray(
    bgr: np.ndarray, depth_m: np.ndarray, stride: int, min_depth_m: float, max_depth_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Every stride-th pixel's depth (float32, 0 outside (min, max)) and 8-bit
    gray, the latter bit-exact with OpenCV's COLOR_BGR2GRAY (its 15-bit fixed
    point: (3735 B + 19235 G + 9798 R + 2^14) >> 15, i.e. 0.114 B + 0.587 G +
    0.299 R; tests/test_kernels.py compares)."""
    rows = (depth_m.shape[0] + stride - 1) // stride
    cols = (depth_m.shape[1] + stride - 1) // stride
    depth = np.zeros((rows, cols), np.float32)
    gray = np.empty((rows, cols), np.uint8)
    for i in range(rows):
        for j in range(cols):
            z = depth_m[i * stride, j * stride]
            if min_depth_m < z < max_depth_m:
                depth[i, j] = z
            b = np.int32(bgr[i * stride, j * stride, 0])
            g = np.int32(bgr[i * stride, j * stride, 1])
            r = np.int32(bgr[i * stride, j * stride, 2])
            gray[i, j] = np.uint8((b * 3735 + g * 19235 + r * 9798 + 16384) >> 15)
    return depth, gray


@njit(cache=True, nogil=True)
def block_means(
    gray: np.ndarray, depth_m: np.ndarray, mask: np.ndarray, down: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean gray and depth over the masked cells of each down x down block
    (whole blocks only; 0 where none), and the masked share of the block."""
    rows, cols = gray.shape[0] // down, gray.shape[1] // down
    g = np.zeros((rows, cols), np.float32)
    z = np.zeros((rows, cols), np.float32)
    cover = np.zeros((rows, cols), np.float32)
    for bi in range(rows):
        for bj in range(cols):
            sg = 0.0
            sz = 0.0
            sm = 0.0
            for i in range(bi * down, bi * down + down):
                for j in range(bj * down, bj * down + down):
                    m = mask[i, j]
                    sm += m
                    sg += gray[i, j] * m
                    sz += depth_m[i, j] * m
            if sm > 0.0:
                g[bi, bj] = sg / sm
                z[bi, bj] = sz / sm
            cover[bi, bj] = sm / (down * down)
    return g, z, cover


@njit(cache=True, nogil=True)
def shutter_rays(rays, depth, tau_rows, wx, wy, wz):
    """Each row's rays and depths turned by tau omega (first order) to the
    middle row's instant (onboard/nislam/shutter.py): (x, y, 1) + tau
    omega x (x, y, 1), renormalised to unit depth, the depth scaled by the
    new z. float32 throughout, one pass (0.26 ms at 320 x 240 against 0.62 ms
    for numpy's temporaries)."""
    rows, cols = depth.shape
    out_rays = np.empty_like(rays)
    out_depth = np.empty_like(depth)
    one = np.float32(1.0)
    for i in range(rows):
        t = tau_rows[i]
        for j in range(cols):
            x = rays[i, j, 0]
            y = rays[i, j, 1]
            xn = x + t * (wy - wz * y)
            yn = y + t * (wz * x - wx)
            zn = one + t * (wx * y - wy * x)
            out_rays[i, j, 0] = xn / zn
            out_rays[i, j, 1] = yn / zn
            out_rays[i, j, 2] = one
            out_depth[i, j] = depth[i, j] * zn
    return out_rays, out_depth


@njit(cache=True, nogil=True, inline="always")
def _slope(depth: np.ndarray, mask: np.ndarray, i: int, j: int, di: int, dj: int) -> float:
    """Depth change per cell at (i, j) along (di, dj): a central difference,
    one-sided where one neighbour is a hole or off the grid, from the cells
    two away where both are, else 0. At ~1 point per cell (pixel_stride 2 at
    1.5 m) a key has holes everywhere: asking for both neighbours left a
    tenth of the cells, the nearest and densest, and t_z drifted on them."""
    h, w = depth.shape
    for k in range(1, 3):
        i0, j0, i1, j1 = i - k * di, j - k * dj, i + k * di, j + k * dj
        lo = i0 >= 0 and j0 >= 0 and mask[i0, j0] > 0
        hi = i1 < h and j1 < w and mask[i1, j1] > 0
        if lo and hi:
            return 0.5 * (depth[i1, j1] - depth[i0, j0]) / k
        if hi:
            return (depth[i1, j1] - depth[i, j]) / k
        if lo:
            return (depth[i, j] - depth[i0, j0]) / k
    return 0.0


@njit(cache=True, nogil=True, inline="always")
def _side_slope(depth: np.ndarray, mask: np.ndarray, i: int, j: int, di: int, dj: int) -> tuple[float, bool]:
    """Depth change per cell from (i, j) toward (di, dj), from the nearest
    filled cell within 2 on that side; (0, False) when there is none."""
    h, w = depth.shape
    for k in range(1, 3):
        i1, j1 = i + k * di, j + k * dj
        if i1 < 0 or j1 < 0 or i1 >= h or j1 >= w:
            break
        if mask[i1, j1] > 0:
            return (depth[i1, j1] - depth[i, j]) / (k * (di + dj)), True
    return 0.0, False


@njit(cache=True, nogil=True, inline="always")
def _limited_slope(depth: np.ndarray, mask: np.ndarray, i: int, j: int, di: int, dj: int) -> tuple[float, float]:
    """The surface's slope at (i, j) along (di, dj) for the carry, and the
    spread of the two one-sided slopes. Both sides filled: the smaller
    one-sided slope if they agree in sign, else 0 (minmod: at a depth edge
    one side is another surface and the flat side is the cell's), and
    |hi - lo| says how unsure the carry is (an edge, or noise). One side:
    its slope, spread 0. A central difference across an edge is half the
    jump, and the carry moved the cell by the sub-cell part times that."""
    hi, has_hi = _side_slope(depth, mask, i, j, di, dj)
    lo, has_lo = _side_slope(depth, mask, i, j, -di, -dj)
    if has_hi and has_lo:
        spread = abs(hi - lo)
        if hi * lo <= 0.0:
            return 0.0, spread
        return (hi if abs(hi) < abs(lo) else lo), spread
    return (hi if has_hi else lo), 0.0


# Index of each sum in depth_difference_sums' result; with weights, every sum
# but N (the count of cells) is weighted and SUM_W is the sum of the weights.
N, SUM_D, SUM_DD, SUM_ZKEY, SUM_X, SUM_Y, SUM_XX, SUM_YY, SUM_XY, SUM_DX, SUM_DY, SUM_W = range(12)


@njit(cache=True, nogil=True)
def depth_difference_sums(
    key_depth: np.ndarray,
    key_mask: np.ndarray,
    key_gray: np.ndarray,
    cur_depth: np.ndarray,
    cur_mask: np.ndarray,
    cur_gray: np.ndarray,
    du: int,
    dv: int,
    gate_gray: float,
    gate_depth_m: float,
    res_m: float,
    min_sample: int,
    frac_u: float = 0.0,
    frac_v: float = 0.0,
    sigma_rel: float = 0.0,
    sigma_floor_m: float = 0.0,
    carry: bool = False,
    step: int = 2,
    gate_sigmas: float = 0.0,
    limited: bool = False,
) -> np.ndarray:
    """Sums over the well-matched cells of Eq. 18, every other row and column
    of the overlap (current cell p + (du, dv) against key cell p).

    Delta = cur_depth - key_depth on cells filled in both whose gray differs
    by less than gate_gray; the depth gate keeps |Delta - median| <
    gate_depth_m, the median taken over every 4th row and column (it only has
    to centre the gate). x, y are the key cell centres in metres from the
    optical axis. Returns the sums indexed by N, SUM_D, ... (all 0 when fewer
    than min_sample cells reach the median).

    With sigma_floor_m > 0 the sums are weighted by the inverse variance of
    Delta, and Delta is carried to the sub-cell shift (frac_u, frac_v) along
    the key's depth gradient g (m per cell, central differences): on a
    surface seen at a slant, a shift rounded to whole cells and the random
    place of each cell's point inside it move Delta by g times the
    misregistration. Delta += frac . g removes the first; the variance
    (sigma_rel z^2, at least sigma_floor_m)^2 + |g|^2 / 6 (a uniform position
    inside the cell, in both images: 2 x 1/12 cell^2 per axis) weighs the
    second, so slanted surfaces and depth edges count little. Cells whose
    four key neighbours are not all filled (hole and frame borders) are left
    out in that mode.
    """
    out = np.zeros(12)
    h, w = key_depth.shape
    weighted = sigma_floor_m > 0.0
    carry = carry or weighted
    ky0, ky1 = max(0, -dv), min(h, h - dv)
    kx0, kx1 = max(0, -du), min(w, w - du)
    if ky1 <= ky0 or kx1 <= kx0:
        return out
    sample = np.empty(((ky1 - ky0 + 3) // 4) * ((kx1 - kx0 + 3) // 4), np.float32)
    n_sample = 0
    for i in range(ky0, ky1, 4):
        for j in range(kx0, kx1, 4):
            if key_mask[i, j] > 0 and cur_mask[i + dv, j + du] > 0:
                if abs(cur_gray[i + dv, j + du] - key_gray[i, j]) < gate_gray:
                    sample[n_sample] = cur_depth[i + dv, j + du] - key_depth[i, j]
                    n_sample += 1
    if n_sample < min_sample:
        return out
    med = np.median(sample[:n_sample])
    for i in range(ky0, ky1, step):
        y = (i - h // 2 + 0.5) * res_m
        for j in range(kx0, kx1, step):
            if not (key_mask[i, j] > 0 and cur_mask[i + dv, j + du] > 0):
                continue
            if not abs(cur_gray[i + dv, j + du] - key_gray[i, j]) < gate_gray:
                continue
            d = cur_depth[i + dv, j + du] - key_depth[i, j]
            wt = 1.0
            gate = gate_depth_m
            if carry:
                spread2 = 0.0
                if limited:  # kernels._limited_slope; its spread into the variance
                    gx, sx = _limited_slope(key_depth, key_mask, i, j, 0, 1)
                    gy, sy = _limited_slope(key_depth, key_mask, i, j, 1, 0)
                    spread2 = sx * sx + sy * sy
                else:
                    gx = _slope(key_depth, key_mask, i, j, 0, 1)
                    gy = _slope(key_depth, key_mask, i, j, 1, 0)
                d += frac_u * gx + frac_v * gy
                if weighted:
                    # The noise's depth from both images (current moved into
                    # the key's axes by the median): from the key's alone, a
                    # cell whose key depth errs near gets more weight and a
                    # larger Delta, a bias of +4 sigma^2 / z; the two errors
                    # enter Delta with opposite signs and cancel in the mean.
                    z = 0.5 * (key_depth[i, j] + cur_depth[i + dv, j + du] - med)
                    sz = max(sigma_rel * z * z, sigma_floor_m)
                    wt = 1.0 / (sz * sz + (gx * gx + gy * gy) / 6.0 + spread2)
                    # The gate no narrower than gate_sigmas times the noise of
                    # the difference: at 5 m (52 mm) a fixed 0.1 m cuts the
                    # noise at 2 sigma around a median of ~100 sampled cells,
                    # and the cut pulls t_z toward that median's error.
                    gate = max(gate, gate_sigmas * 1.4142135 * sz)
            if not abs(d - med) < gate:
                continue
            x = (j - w // 2 + 0.5) * res_m
            out[N] += 1.0
            out[SUM_W] += wt
            out[SUM_D] += wt * d
            out[SUM_DD] += wt * d * d
            out[SUM_ZKEY] += wt * key_depth[i, j]
            out[SUM_X] += wt * x
            out[SUM_Y] += wt * y
            out[SUM_XX] += wt * x * x
            out[SUM_YY] += wt * y * y
            out[SUM_XY] += wt * x * y
            out[SUM_DX] += wt * d * x
            out[SUM_DY] += wt * d * y
    return out


@njit(cache=True, nogil=True)
def refine_key(
    gray_ref: np.ndarray,
    depth_ref: np.ndarray,
    count: np.ndarray,
    cur_gray: np.ndarray,
    cur_depth: np.ndarray,
    cur_mask: np.ndarray,
    du: int,
    dv: int,
    frac_u: float,
    frac_v: float,
    tz: float,
    gate_depth_m: float,
) -> int:
    """Eq. 19 in place: the count-weighted moving average of the key's gray
    and depth with a matched frame (current cell p + (du, dv) against key cell
    p), its depth moved into the key's axes (+ t_z) and carried to the
    sub-cell shift along the key's slope, as in depth_difference_sums. A cell
    the key already holds takes the frame only when the carried depth agrees
    within gate_depth_m (an occluding edge or another surface otherwise; Eq. 18
    gates the same cells); an empty cell takes it as it is. At the whole-cell
    shift without the gate the key's depth on a slanted surface drifted by
    the frames' sub-cell parts times its slope, and its edges by whatever
    lay behind them, and every later t_z against the key inherited both.
    Returns the cells updated. The slopes are those of the key before this
    frame (taken from a copy of the rows the update has not reached)."""
    h, w = depth_ref.shape
    ky0, ky1 = max(0, -dv), min(h, h - dv)
    kx0, kx1 = max(0, -du), min(w, w - du)
    if ky1 <= ky0 or kx1 <= kx0:
        return 0
    before = depth_ref.copy()  # slopes from the key as it was
    filled = count.copy()
    n = 0
    for i in range(ky0, ky1):
        for j in range(kx0, kx1):
            if not cur_mask[i + dv, j + du] > 0:
                continue
            zc = cur_depth[i + dv, j + du] + tz
            c = count[i, j]
            if c > 0:
                gx = _slope(before, filled, i, j, 0, 1)
                gy = _slope(before, filled, i, j, 1, 0)
                zc += frac_u * gx + frac_v * gy
                if not abs(zc - before[i, j]) < gate_depth_m:
                    continue
            c += 1.0
            count[i, j] = c
            gain = 1.0 / c
            gray_ref[i, j] += (cur_gray[i + dv, j + du] - gray_ref[i, j]) * gain
            depth_ref[i, j] += (zc - depth_ref[i, j]) * gain
            n += 1
    return n


def warm_up() -> None:
    """Compile (or load from the disk cache) every kernel for the argument
    types the tracker passes, before the first frame needs them."""
    t0 = time.perf_counter()
    f32 = np.zeros((4, 4), np.float32)
    rays = np.zeros((4, 4, 3), np.float32)
    rays.setflags(write=False)  # as projection._rays hands them out
    zbuffer_project(f32, np.zeros((4, 4), np.uint8), rays, np.zeros((3, 4), np.float32), 2, 2, True)
    zbuffer_project(f32, np.zeros((4, 4), np.uint8), rays, np.zeros((3, 4), np.float32), 2, 2, True,
                    0.01, 0.0045)
    # ... and the rays shutter_rays bends for a rolling shutter (writable)
    zbuffer_project(f32, np.zeros((4, 4), np.uint8), rays.copy(), np.zeros((3, 4), np.float32),
                    2, 2, True, 0.01, 0.0045)
    depth_difference_sums(f32, f32, f32, f32, f32, f32, 0, 0, 0.1, 0.1, 0.01, 1)
    depth_difference_sums(f32, f32, f32, f32, f32, f32, 0, 0, 0.1, 0.1, 0.01, 1, 0.1, 0.1,
                          0.0015, 0.001)
    depth_difference_sums(f32, f32, f32, f32, f32, f32, 0, 0, 0.1, 0.1, 0.01, 1, 0.1, 0.1,
                          0.0015, 0.0, True, 2)
    depth_difference_sums(f32, f32, f32, f32, f32, f32, 0, 0, 0.1, 0.1, 0.01, 1, 0.1, 0.1,
                          0.0015, 0.001, True, 2, 4.0)
    depth_difference_sums(f32, f32, f32, f32, f32, f32, 0, 0, 0.1, 0.1, 0.01, 1, 0.1, 0.1,
                          0.0015, 0.001, True, 2, 4.0, True)
    refine_key(f32.copy(), f32.copy(), f32.copy(), f32, f32, f32, 0, 0, 0.1, 0.1, 0.0, 0.1)
    strided_depth_gray(np.zeros((4, 4, 3), np.uint8), f32, 2, 0.2, 6.0)
    rays = np.zeros((4, 4, 3), np.float32)
    rays.setflags(write=False)  # the shared unit rays (projection._rays) are read-only
    shutter_rays(rays, f32, np.zeros(4, np.float32), np.float32(0.0), np.float32(0.0),
                 np.float32(0.0))
    # Overlap windows are contiguous views when the shift has no column part,
    # strided ones otherwise: both layouts get compiled.
    block_means(f32, f32, f32, 2)
    block_means(f32[:, 1:], f32[:, 1:], f32[:, 1:], 2)
    filter_kernels.warm_up()
    log.debug("compiled kernels ready in %.2f s", time.perf_counter() - t0)
