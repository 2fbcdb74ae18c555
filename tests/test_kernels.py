"""The compiled kernels (onboard/nislam/kernels.py) against plain numpy / OpenCV
statements of what they compute, on random data where a slip in an index, a
gate or a tie rule shows."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from onboard.nislam import filter_kernels
from onboard.nislam import kernels as kern
from onboard.nislam.projection import warped_gray

RNG = np.random.default_rng(5)


def test_strided_depth_gray_is_opencv_gray_and_gated_depth() -> None:
    bgr = RNG.integers(0, 256, (97, 131, 3), dtype=np.uint8)
    depth = RNG.uniform(0.0, 7.0, (97, 131)).astype(np.float32)
    depth[5, 5] = np.nan
    for stride in (1, 2, 3):
        d, g = kern.strided_depth_gray(bgr, depth, stride, 0.2, 6.0)
        assert np.array_equal(g, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)[::stride, ::stride])
        z = depth[::stride, ::stride]
        want = np.where((z > 0.2) & (z < 6.0), z, 0.0).astype(np.float32)
        assert np.array_equal(d, want)


def _zbuffer_reference(depth, gray8, rays, m, h, w):
    """Nearest point per cell by brute force (sort by depth, first wins)."""
    p = rays.reshape(-1, 3).astype(np.float64) * depth.reshape(-1, 1)
    uvz = p @ m[:, :3].T.astype(np.float64) + m[:, 3]
    u, v, z = uvz[:, 0], uvz[:, 1], uvz[:, 2]
    ok = (depth.reshape(-1) > 0) & (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out_d = np.zeros((h, w), np.float32)
    out_g = np.zeros((h, w), np.float32)
    seen = np.zeros((h, w), bool)
    g = gray8.reshape(-1)
    for k in np.flatnonzero(ok)[np.argsort(z[ok], kind="stable")]:
        cell = (int(v[k]), int(u[k]))
        if not seen[cell]:
            seen[cell] = True
            out_d[cell], out_g[cell] = z[k], g[k] / 255.0
    return out_d, out_g, seen


def test_zbuffer_nearest_point_wins_in_every_cell() -> None:
    rows, cols, h, w = 40, 50, 24, 30
    # Many points per cell, at well separated depths so 0.1 mm codes cannot tie.
    depth = RNG.permutation(np.linspace(0.5, 4.0, rows * cols)).reshape(rows, cols).astype(np.float32)
    depth[::7, ::5] = 0.0  # holes are skipped
    gray8 = RNG.integers(0, 256, (rows, cols), dtype=np.uint8)
    rays = np.dstack([
        RNG.uniform(-0.6, 0.6, (rows, cols)), RNG.uniform(-0.5, 0.5, (rows, cols)), np.ones((rows, cols))
    ]).astype(np.float32)
    rot = cv2.Rodrigues(np.array([0.1, -0.2, 0.3]))[0]
    res_m = 0.08
    m = np.zeros((3, 4), np.float32)
    m[:2, :3] = rot[:2] / res_m
    m[2, :3] = rot[2]
    m[:2, 3] = (w // 2, h // 2)
    d, g, mask, winner = kern.zbuffer_project(depth, gray8, rays, m, h, w, True)
    ref_d, ref_g, ref_seen = _zbuffer_reference(depth, gray8, rays, m, h, w)
    assert ref_seen.sum() > 0.5 * h * w  # the test covers most cells
    assert np.array_equal(mask > 0, ref_seen)
    assert np.allclose(d, ref_d, atol=1.5e-4)  # 0.1 mm depth code
    assert np.allclose(g, ref_g, atol=1e-6)
    # The winner index names the pixel whose gray and depth the cell holds.
    filled = winner >= 0
    assert np.array_equal(filled.reshape(h, w), ref_seen)
    assert np.allclose(gray8.reshape(-1)[winner[filled]] / 255.0, g.reshape(-1)[filled], atol=1e-6)


def _sums_reference(kd, km, kg, cd, cm, cg, du, dv, gate_gray, gate_depth, res_m):
    h, w = kd.shape
    ky, kx = slice(max(0, -dv), min(h, h - dv), 2), slice(max(0, -du), min(w, w - du), 2)
    cy = slice(ky.start + dv, ky.stop + dv, 2)
    cx = slice(kx.start + du, kx.stop + du, 2)
    delta = (cd[cy, cx] - kd[ky, kx]).astype(np.float64)
    seen = (cm[cy, cx] > 0) & (km[ky, kx] > 0) & (np.abs(cg[cy, cx] - kg[ky, kx]) < gate_gray)
    med = np.median(delta[::2, ::2][seen[::2, ::2]])
    inl = seen & (np.abs(delta - med) < gate_depth)
    ys, xs = np.mgrid[ky, kx]
    x = (xs - w // 2 + 0.5) * res_m
    y = (ys - h // 2 + 0.5) * res_m
    d, zk, x, y = delta[inl], kd[ky, kx][inl].astype(np.float64), x[inl], y[inl]
    return np.array([
        len(d), d.sum(), (d * d).sum(), zk.sum(), x.sum(), y.sum(),
        (x * x).sum(), (y * y).sum(), (x * y).sum(), (d * x).sum(), (d * y).sum(),
    ])


@pytest.mark.parametrize("du, dv", [(0, 0), (7, -3), (-12, 9)])
def test_depth_difference_sums_match_numpy(du: int, dv: int) -> None:
    h, w = 60, 80
    kd = RNG.uniform(1.0, 3.0, (h, w)).astype(np.float32)
    km = (RNG.random((h, w)) > 0.2).astype(np.float32)
    kg = RNG.random((h, w)).astype(np.float32)
    cd = (np.roll(kd, (dv, du), axis=(0, 1)) + 0.05 + RNG.normal(0, 0.01, (h, w))).astype(np.float32)
    cd[RNG.random((h, w)) < 0.1] += 1.0  # outliers the depth gate must reject
    cm = (RNG.random((h, w)) > 0.2).astype(np.float32)
    cg = (np.roll(kg, (dv, du), axis=(0, 1)) + RNG.normal(0, 0.06, (h, w))).astype(np.float32)
    args = (kd, km, kg, cd, cm, cg, du, dv, 0.1, 0.1, 0.01)
    got = kern.depth_difference_sums(*args, 1)
    want = _sums_reference(*args)
    assert 100 < got[kern.N] < 0.25 * h * w
    assert np.allclose(got[:kern.SUM_W], want, rtol=1e-6, atol=1e-9)
    assert got[kern.SUM_W] == got[kern.N]  # unweighted: weights of 1
    # Too few cells for the median: nothing is summed.
    assert not kern.depth_difference_sums(*args, 10**6).any()


@pytest.mark.parametrize("window", [np.s_[:, :], np.s_[3:, 5:]])
def test_block_means_are_masked_block_averages(window) -> None:
    gray = RNG.random((37, 50)).astype(np.float32)[window]
    depth = RNG.uniform(1.0, 3.0, (37, 50)).astype(np.float32)[window]
    mask = (RNG.random((37, 50)) > 0.85).astype(np.float32)[window]
    g, z, cover = kern.block_means(gray, depth, mask, 4)
    h, w = gray.shape[0] // 4, gray.shape[1] // 4
    blocks = lambda a: a[: 4 * h, : 4 * w].reshape(h, 4, w, 4).sum(axis=(1, 3))  # noqa: E731
    n = blocks(mask)
    assert np.allclose(cover, n / 16.0)
    assert (n == 0).any() and (n > 0).any()  # empty blocks are covered by the test
    with np.errstate(invalid="ignore", divide="ignore"):
        assert np.allclose(g, np.where(n > 0, blocks(gray * mask) / n, 0.0), atol=1e-6)
        assert np.allclose(z, np.where(n > 0, blocks(depth * mask) / n, 0.0), atol=1e-6)


# A slanted plane (key depth) and the same plane seen after a shift by
# (du + fu, dv + fv) cells and t_z along the axis (current depth).
PLANE_SHIFT = (3, -2, 0.3, -0.4, 0.02)  # du, dv, fu, fv [cells], t_z [m]


def _shifted_plane() -> tuple[np.ndarray, np.ndarray, tuple]:
    du, dv, fu, fv, tz = PLANE_SHIFT
    vv, uu = np.mgrid[0:40, 0:50].astype(np.float64)
    plane = lambda u, v: 2.0 + 0.01 * u + 0.005 * v  # noqa: E731
    kd = plane(uu, vv).astype(np.float32)
    cd = (plane(uu - du - fu, vv - dv - fv) - tz).astype(np.float32)
    return kd, cd, PLANE_SHIFT


def test_weighted_depth_sums_carry_differences_to_the_sub_cell_shift() -> None:
    """A slanted plane shifted by a non-integer number of cells: carried along
    the key's depth gradient to the sub-cell shift, every difference is -t_z
    exactly (a plane's central differences are exact); at the whole-cell shift
    (the paper's mean) the slope times the rounding biases it."""
    kd, cd, (du, dv, fu, fv, tz) = _shifted_plane()
    ones = np.ones_like(kd)
    args = (kd, ones, ones, cd, ones, ones, du, dv, 0.1, 0.1, 0.01, 1)
    got = kern.depth_difference_sums(*args, fu, fv, 0.0015, 0.001)
    assert got[kern.N] > 100
    assert got[kern.SUM_D] / got[kern.SUM_W] == pytest.approx(-tz, abs=2e-6)
    plain = kern.depth_difference_sums(*args)
    assert plain[kern.SUM_W] == plain[kern.N]  # unweighted: weights of 1
    bias = -(fu * 0.01 + fv * 0.005)
    assert plain[kern.SUM_D] / plain[kern.N] == pytest.approx(-tz + bias, abs=2e-6)


def test_warped_gray_is_the_gray_of_the_homography_image() -> None:
    """Identity: the strided gray; a shift by whole pixels: the shifted gray."""
    bgr = (RNG.random((48, 64, 3)) * 255).astype(np.uint8)
    depth = np.ones((48, 64), np.float32)
    _, gray = kern.strided_depth_gray(bgr, depth, 2, 0.1, 5.0)
    assert np.abs(warped_gray(bgr, 2, np.eye(3)).astype(int) - gray).max() <= 1
    shift = np.array([[1.0, 0.0, 4.0], [0.0, 1.0, 2.0], [0.0, 0.0, 1.0]])
    warped = warped_gray(bgr, 2, shift).astype(int)
    assert np.abs(warped[:-1, :-2] - gray[1:, 2:]).max() <= 1


def test_depth_sums_carry_keeps_cells_next_to_holes() -> None:
    """At ~1 point per cell a key has holes everywhere: the slope is taken
    one-sided next to a hole, or from the cells two away, so the carry keeps
    every matched cell and removes the rounding bias on a plane. Asking for
    all four neighbours kept ~1/16 of them here (and let t_z drift on the
    few dense ones)."""
    kd, cd, (du, dv, fu, fv, tz) = _shifted_plane()
    ones = np.ones_like(kd)
    km = (RNG.random(kd.shape) > 0.5).astype(np.float32)
    args = (kd, km, ones, cd, ones, ones, du, dv, 0.1, 0.1, 0.01, 1)
    plain = kern.depth_difference_sums(*args, 0.0, 0.0, 0.0, 0.0, False, 1)
    carried = kern.depth_difference_sums(*args, fu, fv, 0.0, 0.0, True, 1)
    assert carried[kern.N] >= 0.95 * plain[kern.N]
    bias = -(fu * 0.01 + fv * 0.005)
    assert plain[kern.SUM_D] / plain[kern.N] == pytest.approx(-tz + bias, abs=2e-6)
    # Cells with no filled cell within two on an axis (1/16 here) keep the bias.
    carried_bias = carried[kern.SUM_D] / carried[kern.SUM_W] + tz
    assert abs(carried_bias) < abs(bias) / 8


def test_correlation_kernels_give_numpys_bits() -> None:
    """The filter's one-pass kernels reproduce the numpy passes they replaced
    bit for bit (the poses of every replay stay byte-identical): the kernel's
    exponent (NaN kept), the whitened gray, and the lobe's 4-connected region
    around the window's centre as scipy.ndimage.label finds it."""
    from scipy import ndimage

    rng = np.random.default_rng(3)
    k = (rng.standard_normal((36, 48)) * 300.0).astype(np.float32)
    k[5, 7] = np.nan
    sq, scale = np.float32(250.0), np.float32(-3.1e-4)
    want = k * np.float32(-2.0)
    want += sq
    np.maximum(want, np.float32(0.0), out=want)
    want *= scale
    got = filter_kernels.kernel_exponent(k.copy(), sq, scale)
    assert np.array_equal(got, want, equal_nan=True) and np.isnan(got[5, 7])

    gray = rng.random((36, 48)).astype(np.float32)
    mask = (rng.random((36, 48)) > 0.4).astype(np.float32)
    want = gray - np.float32(0.37)
    want *= mask
    assert np.array_equal(filter_kernels.masked_centred(gray, mask, np.float32(0.37)), want)

    for _ in range(20):
        above = rng.standard_normal((25, 25))
        above[12, 12] = abs(above[12, 12]) + 0.1
        labels, _n = ndimage.label(above > 0.0)
        region = filter_kernels.connected_above(above)
        assert np.array_equal(region == 1, labels == labels[12, 12])
    above[12, 12] = -1.0  # the centre below: no region
    assert not filter_kernels.connected_above(above).any()
