"""Axonometric projection of RGB-D clouds (NI-SLAM Sec. IV-A) and the adaptive
cell size (authors' adapt_field_of_view, reference-nislam.md §3).

Cell convention under test (onboard/nislam/projection.py): cell u covers
x' in [(u - W//2) res, (u + 1 - W//2) res) (floor), likewise v; p' = R p.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from onboard.core.camera import CameraIntrinsics
from onboard.nislam.correlation import KernelCorrelationFilter, find_peak
from onboard.nislam.projection import Cloud, adaptive_resolution, make_cloud, project
from onboard.nislam.sampling import stride_for_grid

INTR = CameraIntrinsics(fx=500, fy=500, cx=319.5, cy=239.5, width=640, height=480)
MIN_D, MAX_D = 0.2, 6.0


def _rays_f64(intr: CameraIntrinsics = INTR):
    u = (np.arange(intr.width) - intr.cx) / intr.fx
    v = (np.arange(intr.height) - intr.cy) / intr.fy
    return np.broadcast_to(u[None, :], (intr.height, intr.width)), np.broadcast_to(
        v[:, None], (intr.height, intr.width)
    )


def _cloud_with_rays(rays: np.ndarray, gray: int = 128) -> Cloud:
    """A 1 x n cloud at depth 1 m whose camera-frame points are exactly `rays`
    (float32 (1, n, 3)): built by make_cloud, then its rays replaced, so the
    test does not depend on Cloud's other fields."""
    n = rays.shape[1]
    intr = CameraIntrinsics(fx=1.0, fy=1.0, cx=0.0, cy=0.0, width=n, height=1)
    base = make_cloud(
        np.full((1, n, 3), gray, np.uint8), np.ones((1, n), np.float32), intr, MIN_D, MAX_D
    )
    return dataclasses.replace(base, rays=np.ascontiguousarray(rays, np.float32))


def _expected_cell(p_key: np.ndarray, shape, res):
    """(v, u) of a key-axes point under the floor convention, plus its distance
    to the nearest cell border in cells (to keep test points off borders)."""
    h, w = shape
    fu, fv = p_key[0] / res, p_key[1] / res
    border = min(abs(fu - round(fu)), abs(fv - round(fv)))
    return (math.floor(fv) + h // 2, math.floor(fu) + w // 2), border


# ------------------------------------------------------------ lateral translation
# Plane at 2 m: pixel rays hit it at x = (k + 1/2) * 4 mm = odd multiples of 2 mm.
# With res = 8 mm the cell borders are multiples of 8 mm = even multiples of 2 mm,
# so no ray lands on a border (all >= 1/4 cell away) and float32 round-off cannot
# move a point into the neighbouring cell. (res = 1 cm would put rays exactly on
# borders: 5 x 2 mm = 1 cm.)
PLANE_Z = 2.0
RES = 0.008
SHAPE = (180, 240)  # +-0.72 m x +-0.96 m: inside the camera's view at 2 m
T_CAM = (0.048, -0.024)  # 6 and -3 cells; content moves by (-6, +3) cells
TEX_OFF = 400  # world cell index offset into the texture table


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    """Random BGR colour per 8 mm world cell on the plane, indexed [iy+off, ix+off]."""
    return np.random.default_rng(11).integers(0, 256, (2 * TEX_OFF, 2 * TEX_OFF, 3), dtype=np.uint8)


def _render_plane(texture, cam_x: float, cam_y: float):
    """Ray-cast the textured plane z = PLANE_Z (world) from a camera at
    (cam_x, cam_y, 0) with the world's orientation: the texture is fixed in the
    world, so it really moves in the image when the camera moves."""
    rx, ry = _rays_f64()
    x_w = cam_x + rx * PLANE_Z
    y_w = cam_y + ry * PLANE_Z
    ix = np.floor(x_w / RES).astype(int) + TEX_OFF
    iy = np.floor(y_w / RES).astype(int) + TEX_OFF
    bgr = np.ascontiguousarray(texture[iy, ix])
    return bgr, np.full((INTR.height, INTR.width), PLANE_Z, np.float32)


def overlap(img, du, dv):
    """(key part, current part) with current[v + dv, u + du] against key[v, u]."""
    h, w = img.shape
    return (
        (slice(max(0, -dv), h - max(0, dv)), slice(max(0, -du), w - max(0, du))),
        (slice(max(0, dv), h - max(0, -dv)), slice(max(0, du), w - max(0, -du))),
    )


def test_fronto_parallel_plane_cells_hold_the_world_texture(texture):
    """Key view: every cell filled at 2 m, and cell (v, u) shows exactly the
    world texture cell (u - W/2, v - H/2) with the gray of OpenCV's BGR2GRAY
    (the authors' 0.114 B + 0.587 G + 0.299 R), scaled to [0, 1]."""
    bgr, depth = _render_plane(texture, 0.0, 0.0)
    img = project(make_cloud(bgr, depth, INTR, MIN_D, MAX_D), np.eye(3), SHAPE, RES)
    h, w = SHAPE
    assert img.res_m == RES
    assert img.mask.dtype == np.float32 and np.all(img.mask == 1.0)
    np.testing.assert_allclose(img.depth_m, PLANE_Z, atol=1e-4)  # 0.1 mm depth code
    gray_tex = cv2.cvtColor(texture, cv2.COLOR_BGR2GRAY)
    rows = slice(TEX_OFF - h // 2, TEX_OFF + h - h // 2)
    cols = slice(TEX_OFF - w // 2, TEX_OFF + w - w // 2)
    want = gray_tex[rows, cols]
    np.testing.assert_allclose(img.gray, want / 255.0, rtol=0, atol=1e-6)  # 1 gray level = 3.9e-3


def test_lateral_translation_shifts_axonometric_image_by_exact_cells(texture):
    key_bgr, key_depth = _render_plane(texture, 0.0, 0.0)
    cur_bgr, cur_depth = _render_plane(texture, *T_CAM)
    key = project(make_cloud(key_bgr, key_depth, INTR, MIN_D, MAX_D), np.eye(3), SHAPE, RES)
    cur = project(make_cloud(cur_bgr, cur_depth, INTR, MIN_D, MAX_D), np.eye(3), SHAPE, RES)
    du, dv = round(-T_CAM[0] / RES), round(-T_CAM[1] / RES)
    assert (du, dv) == (-6, 3)
    ks, cs = overlap(key.gray, du, dv)
    assert key.gray[ks].size > 0.9 * key.gray.size
    np.testing.assert_array_equal(cur.gray[cs], key.gray[ks])
    np.testing.assert_array_equal(cur.depth_m[cs], key.depth_m[ks])
    # ... and not by a neighbouring shift (the texture is random per cell)
    ks1, cs1 = overlap(key.gray, du + 1, dv)
    assert np.mean(cur.gray[cs1] == key.gray[ks1]) < 0.1

    # The correlation filter sees the same shift (content moved left/down).
    filt = KernelCorrelationFilter(SHAPE, 0.2, 0.1, 1.0)
    filt.train(key.gray - key.gray.mean())
    peak = find_peak(filt.response(cur.gray - cur.gray.mean()), 5)
    assert abs(peak.du_cells - du) < 0.05  # measured -6.0004
    assert abs(peak.dv_cells - dv) < 0.05  # measured 2.9996


# ------------------------------------------------------------ z-buffer
@pytest.mark.parametrize("near_gray,far_gray", [(200, 50), (50, 200)])
def test_zbuffer_near_surface_covers_far_surface(near_gray, far_gray):
    """A near frame (1 m) with a window through which a far wall (3 m) is seen.
    Orthographically, the far wall seen through the window spreads over cells
    the near frame also covers: those cells must hold the near depth and the
    near gray whichever is brighter; cells only the far wall reaches hold it.
    (1 m and 3 m with res 1 cm: rays hit odd multiples of 1 mm / 3 mm, never a
    cell border.)"""
    res, shape = 0.01, (160, 200)
    rx, ry = _rays_f64()
    px, py = np.meshgrid(np.arange(INTR.width), np.arange(INTR.height))
    window = (np.abs(px - INTR.cx) < 100) & (np.abs(py - INTR.cy) < 80)
    depth = np.where(window, 3.0, 1.0).astype(np.float32)
    gray = np.where(window, far_gray, near_gray).astype(np.uint8)
    bgr = np.repeat(gray[..., None], 3, axis=2)
    img = project(make_cloud(bgr, depth, INTR, MIN_D, MAX_D), np.eye(3), shape, res)

    h, w = shape

    def cells(sel):
        z = depth[sel].astype(np.float64)
        u = np.floor(rx[sel] * z / res).astype(int) + w // 2
        v = np.floor(ry[sel] * z / res).astype(int) + h // 2
        ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        out = np.zeros(shape, bool)
        out[v[ok], u[ok]] = True
        return out

    near, far = cells(~window), cells(window)
    both = near & far
    assert both.sum() > 2000  # the surfaces really overlap in the grid
    np.testing.assert_allclose(img.depth_m[both], 1.0, atol=1e-4)
    np.testing.assert_allclose(img.gray[both], near_gray / 255.0, rtol=0, atol=1e-6)
    far_only = far & ~near
    assert far_only.sum() > 500
    np.testing.assert_allclose(img.depth_m[far_only], 3.0, atol=1e-4)
    np.testing.assert_allclose(img.gray[far_only], far_gray / 255.0, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(img.mask, (near | far).astype(np.float32))
    # holes are 0 in gray and depth
    assert np.all(img.gray[~(near | far)] == 0) and np.all(img.depth_m[~(near | far)] == 0)


# ------------------------------------------------------------ rotation, cell convention
def _sparse_frame(points):
    """Depth/colour images with only the given (px, py, z, gray) pixels valid."""
    depth = np.zeros((INTR.height, INTR.width), np.float32)
    bgr = np.zeros((INTR.height, INTR.width, 3), np.uint8)
    for px, py, z, g in points:
        depth[py, px] = z
        bgr[py, px] = g
    return bgr, depth


def _camera_point(px, py, z):
    return np.array([(px - INTR.cx) / INTR.fx * z, (py - INTR.cy) / INTR.fy * z, z])


def test_rotation_90_deg_about_optical_axis_maps_point_to_floor_cell():
    """Rz(90 deg): (x, y, z) -> (-y, x, z). Pixel (100, 400) at 1.5 m is
    (-0.6585, 0.4815, 1.5) m -> (-0.4815, -0.6585, 1.5) -> (-24.075, -32.925)
    cells at 2 cm: floor gives u = W/2 - 25, v = H/2 - 33 (C++ truncation
    would give -24 / -32; R^T instead of R would land at u = W/2 + 24)."""
    res, shape = 0.02, (100, 120)
    r = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    bgr, depth = _sparse_frame([(100, 400, 1.5, 77)])
    img = project(make_cloud(bgr, depth, INTR, MIN_D, MAX_D), r, shape, res)
    filled = np.argwhere(img.mask > 0)
    assert filled.tolist() == [[100 // 2 - 33, 120 // 2 - 25]]
    v, u = filled[0]
    assert img.depth_m[v, u] == pytest.approx(1.5, abs=1e-4)
    assert img.gray[v, u] == pytest.approx(77 / 255)


def test_general_rotation_maps_points_to_predicted_cells():
    res, shape = 0.02, (240, 200)
    r = Rotation.from_euler("xyz", [20.0, -15.0, 90.0], degrees=True).as_matrix()
    pix = [
        (20, 30, 1.2, 10), (600, 50, 2.7, 60), (330, 250, 0.9, 110),
        (150, 450, 3.3, 160), (500, 420, 1.7, 210),
    ]
    bgr, depth = _sparse_frame(pix)
    img = project(make_cloud(bgr, depth, INTR, MIN_D, MAX_D), r, shape, res)
    want = np.zeros(shape, np.float32)
    for px, py, z, g in pix:
        p_key = r @ _camera_point(px, py, z)
        (v, u), border = _expected_cell(p_key, shape, res)
        assert border > 0.01 and 0 <= u < shape[1] and 0 <= v < shape[0]  # test design
        want[v, u] = 1.0
        assert img.depth_m[v, u] == pytest.approx(p_key[2], abs=2e-4)
        assert img.gray[v, u] == pytest.approx(g / 255)
    np.testing.assert_array_equal(img.mask, want)


# ------------------------------------------------------------ invalid / out of range
def test_invalid_and_out_of_range_depth_produce_no_cells():
    depth = np.full((INTR.height, INTR.width), np.nan, np.float32)
    depth[:, :100] = 0.0  # no measurement
    depth[:, 100:200] = 0.1  # below min_depth
    depth[:, 200:300] = 7.0  # beyond max_depth
    depth[:, 300:400] = np.inf
    depth[:, 400:500] = -1.0
    # rest NaN
    bgr = np.full((INTR.height, INTR.width, 3), 255, np.uint8)
    cloud = make_cloud(bgr, depth, INTR, MIN_D, MAX_D)
    assert len(cloud) == 0
    img = project(cloud, np.eye(3), (120, 160), 0.02)
    assert img.mask.sum() == 0 and np.all(img.depth_m == 0) and np.all(img.gray == 0)

    depth[240, 320] = 2.5  # one valid pixel -> exactly one cell
    cloud = make_cloud(bgr, depth, INTR, MIN_D, MAX_D)
    assert len(cloud) == 1
    img = project(cloud, np.eye(3), (120, 160), 0.02)
    assert img.mask.sum() == 1
    assert img.depth_m.max() == pytest.approx(2.5, abs=1e-4)


def test_points_outside_the_grid_are_dropped_not_wrapped():
    """x'/res just below -W/2 (cell -1), far below (-W/2 - W - 0.5, where a
    plain float->int truncation of x'/res + W/2 + W lands on 0) and at
    W/2 + 0.5 (cell W): none may appear (no clipping, no circular wrap)."""
    res, shape = 0.01, (40, 60)
    w = shape[1]
    xs = [(-w / 2 - 0.5) * res, (-w / 2 - w - 0.5) * res, (w / 2 + 0.5) * res]
    rays = np.array([[[x, 0.001, 1.0] for x in xs]], np.float32)  # depth 1 m: X = x
    img = project(_cloud_with_rays(rays), np.eye(3), shape, res)
    assert img.mask.sum() == 0
    # the same points scaled into the grid do produce one cell each
    inside = rays * np.array([0.1, 1.0, 1.0], np.float32)
    assert project(_cloud_with_rays(inside), np.eye(3), shape, res).mask.sum() == len(xs)


# ------------------------------------------------------------ adaptive resolution
def _cloud_from_xy(xy):
    """A 1 x n cloud at depth 1 m whose camera X, Y are exactly `xy`."""
    rays = np.ones((1, len(xy), 3), np.float32)
    rays[0, :, :2] = np.asarray(xy, np.float64)
    return _cloud_with_rays(rays)


def test_adaptive_resolution_hand_computed():
    """max_distance 4 m, len_hist 50, VGA aspect tau = 3/4: cos = 0.8, sin = 0.6,
    A_w = round(50 * 0.8) = 40, A_h = 30, r_h = 4 / 40 / 2 = 0.05 m.

    4 x (+0.07, +0.01): a = |int(1.4)| = 1, b = 0 -> bin round(1 / 0.8) = 1
    4 x (-0.07, -0.01): int() truncates toward zero -> a = 1 -> bin 1
        (a floor would give a = 2 -> bin 2 or 3)
    2 x (0.01, 0.33):   a = 0, b = int(6.6) = 6 > 0 -> bin round(6 / 0.6) = 10
    cumulative: bin 1 -> 8, bin 10 -> 10 (of 10 points).
    mu = 0.5: 8 > 5 -> k = 1 -> s = 2 * 2 * 0.05 / W
    mu = 0.85: 8 <= 8.5, 10 > 8.5 -> k = 10 -> s = 2 * 11 * 0.05 / W
    mu >= 1 -> k = len_hist = 50 -> s = 2 * 51 * 0.05 / W.
    """
    cloud = _cloud_from_xy([(0.07, 0.01)] * 4 + [(-0.07, -0.01)] * 4 + [(0.01, 0.33)] * 2)
    w = 100

    def s(mu):
        return adaptive_resolution(cloud, w, mu, 4.0, 50, 1)

    assert s(0.5) == pytest.approx(2 * 2 * 0.05 / w, rel=1e-9)
    assert s(0.85) == pytest.approx(2 * 11 * 0.05 / w, rel=1e-9)
    assert s(1.0) == pytest.approx(2 * 51 * 0.05 / w, rel=1e-9)
    assert s(100.0) == pytest.approx(2 * 51 * 0.05 / w, rel=1e-9)


def _plane_cloud(z: float) -> Cloud:
    depth = np.full((INTR.height, INTR.width), z, np.float32)
    bgr = np.full((INTR.height, INTR.width, 3), 128, np.uint8)
    return make_cloud(bgr, depth, INTR, MIN_D, MAX_D)


def test_adaptive_resolution_smaller_cells_for_closer_plane():
    """The grid must hold ~mu of the points; a plane at 1 m spans 2.5x less
    than at 2.5 m, so its cells are ~2.5x smaller (measured 0.00292 vs 0.00750
    m/cell with W = 480, mu = 0.8)."""
    near = adaptive_resolution(_plane_cloud(1.0), 480, 0.8, 4.0, 50, 5)
    far = adaptive_resolution(_plane_cloud(2.5), 480, 0.8, 4.0, 50, 5)
    assert near < 0.6 * far
    # both are of the form 2 (k + 1) r_h / W with integer k
    for s in (near, far):
        k1 = s * 480 / (2 * 0.05)
        assert abs(k1 - round(k1)) < 1e-9


def test_stride_for_grid_samples_about_a_point_per_cell():
    """9 mm cells, f = 525 px: at 4.5 m every 2nd pixel lands 1.9 cells apart
    (one cell in four filled), so a key there takes every pixel; at 1 m (0.42
    cells apart) every 2nd pixel is plenty. 0 (the default) or no depth: the
    configured step."""
    assert stride_for_grid(0.009, 4.5, 525.0, 2, 1.0) == 1
    assert stride_for_grid(0.009, 1.0, 525.0, 2, 1.0) == 2
    assert stride_for_grid(0.009, 1.0, 525.0, 4, 1.0) == 4
    assert stride_for_grid(0.009, 2.0, 525.0, 4, 1.0) == 2  # 2 z / f = 0.85 cells; 3 would be 1.3
    assert stride_for_grid(0.009, 4.5, 525.0, 2, 0.0) == 2
    assert stride_for_grid(0.009, float("nan"), 525.0, 2, 1.0) == 2
