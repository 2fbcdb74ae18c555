"""Synthetic scenes and the analytic renderer: exact depth, z-buffer, geometry
consistency between frames, textures."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from onboard.core.camera import CameraIntrinsics
from onboard.core.rotations import mount_rotation
from sim_replay.flights import Flight, scenario
from sim_replay.render import NEAR_M, Renderer
from sim_replay.scene import Scene, make_scene, plane_scene
from sim_replay.textures import make_texture, mip_levels

INTR = CameraIntrinsics(262.5, 262.5, 159.5, 119.5, 320, 240)
R_B_C = mount_rotation("forward")


def _rays_C(intr: CameraIntrinsics) -> np.ndarray:
    """(H, W, 3) rays with unit z through the pixel centres."""
    u, v = np.meshgrid(np.arange(intr.width, dtype=np.float64),
                       np.arange(intr.height, dtype=np.float64))
    return np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], axis=-1)


def _ray_cast(scene: Scene, R_W_C: np.ndarray, p_W: np.ndarray, rays_C: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """Reference ray caster, independent of the renderer: for every ray the
    nearest surface hit inside its rectangle, seen from its front.
    Returns (depth along the optical axis, surface index or -1)."""
    d_W = rays_C @ R_W_C.T
    best = np.full(rays_C.shape[:-1], np.inf)
    ids = np.full(rays_C.shape[:-1], -1)
    for i, s in enumerate(scene.surfaces):
        n = s.normal
        denom = d_W @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (n @ (s.origin_W_m - p_W)) / denom  # rays have unit z: this is depth
        x = p_W + z[..., None] * d_W - s.origin_W_m
        a, b = x @ s.axis_u, x @ s.axis_v
        hit = ((denom < 0) & (z > NEAR_M) & (a >= 0) & (a <= s.size_m[0]) & (b >= 0)
               & (b <= s.size_m[1]) & (z < best))
        best[hit], ids[hit] = z[hit], i
    return np.where(ids >= 0, best, 0.0), ids


@pytest.fixture(scope="module")
def room_renderer() -> Renderer:
    # Coarse texels: these tests check geometry, and a 1 cm texture builds fast.
    return Renderer(make_scene("room"), INTR, seed=3, texel_m=0.01)


def _circle_pose(t_s: float) -> tuple[np.ndarray, np.ndarray]:
    p, r_w_b = Flight(scenario("circle")).body_pose([t_s])
    return r_w_b[0] @ R_B_C, p[0]


def test_plane_depth_matches_the_analytic_value():
    scene = plane_scene(distance_m=2.0, size_m=8.0)
    renderer = Renderer(scene, INTR, texel_m=0.02)
    R_W_C = Rotation.from_euler("zyx", [12.0, -7.0, 5.0], degrees=True).as_matrix() @ R_B_C
    p_W = np.array([0.3, -0.2, 0.1])
    out = renderer.render(R_W_C, p_W, with_ids=True)
    # Plane x = 2 facing -x: depth z along the optical axis solves p_x + z (R r)_x = 2.
    d_W = _rays_C(INTR) @ R_W_C.T
    expected = (2.0 - p_W[0]) / d_W[..., 0]
    assert (out.surface_id == 0).all() and (out.depth_m > 0).all()
    err = np.abs(out.depth_m.astype(np.float64) - expected)
    assert err.max() < 1e-6, err.max()
    assert 1.4 < expected.min() and expected.max() - expected.min() > 0.5  # a tilted view


def test_room_depth_and_visibility_match_a_reference_ray_caster(room_renderer):
    for t_s in (0.0, 3.7, 9.1):
        R_W_C, p_W = _circle_pose(t_s)
        out = room_renderer.render(R_W_C, p_W, with_ids=True)
        ref_depth, ref_ids = _ray_cast(room_renderer.scene, R_W_C, p_W, _rays_C(INTR))
        assert (ref_ids >= 0).all() and (out.depth_m > 0).all()  # a closed room: no holes
        same = out.surface_id == ref_ids
        # Rasterised outlines may take a pixel whose centre lies a hair outside
        # the surface: only silhouette pixels may disagree.
        assert same.mean() > 0.99, same.mean()
        # Wherever a surface is drawn, its depth is that plane's, exactly.
        err = np.abs(out.depth_m.astype(np.float64) - ref_depth)[same]
        assert err.max() < 1e-6 * ref_depth.max(), err.max()
        # A pixel labelled with another surface than the reference sits next to
        # a pixel where both agree on that other surface (an outline, not a hole).
        bad_v, bad_u = np.nonzero(~same)
        for v, u in zip(bad_v[:200], bad_u[:200]):
            win = slice(max(v - 1, 0), v + 2), slice(max(u - 1, 0), u + 2)
            assert (ref_ids[win] == out.surface_id[v, u]).any()


def test_pixel_reprojected_with_groundtruth_lands_on_the_same_surface_point(room_renderer):
    (R_a, p_a), (R_b, p_b) = _circle_pose(5.0), _circle_pose(5.0 + 2 / 30.0)
    a = room_renderer.render(R_a, p_a, with_ids=True)
    b = room_renderer.render(R_b, p_b, with_ids=True)
    rays = _rays_C(INTR)
    vv, uu = np.mgrid[8:INTR.height - 8:6, 8:INTR.width - 8:6]
    vv, uu = vv.ravel(), uu.ravel()
    # Back-project from frame a, move into frame b with the true poses.
    X_W = p_a + (rays[vv, uu] * a.depth_m[vv, uu, None]) @ R_a.T
    X_b = (X_W - p_b) @ R_b  # R_b^T (X - p_b), row-wise
    u_b = X_b[:, 0] / X_b[:, 2] * INTR.fx + INTR.cx
    v_b = X_b[:, 1] / X_b[:, 2] * INTR.fy + INTR.cy
    inside = (u_b > 2) & (u_b < INTR.width - 3) & (v_b > 2) & (v_b < INTR.height - 3)
    u0, v0 = np.floor(u_b).astype(int), np.floor(v_b).astype(int)
    # Interior points only: the same surface on the 2x2 neighbours in both frames.
    id_a = a.surface_id[vv, uu]
    ok = inside.copy()
    for dv in (0, 1):
        for du in (0, 1):
            ok[inside] &= b.surface_id[v0[inside] + dv, u0[inside] + du] == id_a[inside]
    assert ok.mean() > 0.8  # two frames apart: most of the view is shared
    # Depth at the landing point is the point's own. On a plane 1/z is affine in
    # (u, v), so its bilinear interpolation from frame b's pixels is exact.
    fu, fv = u_b[ok] - u0[ok], v_b[ok] - v0[ok]
    w = 1.0 / b.depth_m.astype(np.float64)
    w_b = ((1 - fu) * (1 - fv) * w[v0[ok], u0[ok]] + fu * (1 - fv) * w[v0[ok], u0[ok] + 1]
           + (1 - fu) * fv * w[v0[ok] + 1, u0[ok]] + fu * fv * w[v0[ok] + 1, u0[ok] + 1])
    assert np.abs(1.0 / w_b - X_b[ok, 2]).max() < 1e-5
    # And it shows the same texture: colours agree far better than at a wrong place.
    g_a = a.bgr.astype(np.float64).mean(axis=2)
    g_b = b.bgr.astype(np.float64).mean(axis=2)
    c_b = ((1 - fu) * (1 - fv) * g_b[v0[ok], u0[ok]] + fu * (1 - fv) * g_b[v0[ok], u0[ok] + 1]
           + (1 - fu) * fv * g_b[v0[ok] + 1, u0[ok]] + fu * fv * g_b[v0[ok] + 1, u0[ok] + 1])
    c_a = g_a[vv[ok], uu[ok]]
    shifted = g_b[np.clip(v0[ok] + 5, 0, INTR.height - 1), u0[ok]]
    assert np.median(np.abs(c_b - c_a)) < 0.3 * np.median(np.abs(shifted - c_a))


def test_rendering_is_deterministic_and_textures_follow_the_seed(room_renderer):
    R_W_C, p_W = _circle_pose(2.0)
    one = room_renderer.render(R_W_C, p_W)
    again = Renderer(room_renderer.scene, INTR, seed=3, texel_m=0.01).render(R_W_C, p_W)
    other = Renderer(room_renderer.scene, INTR, seed=4, texel_m=0.01).render(R_W_C, p_W)
    assert np.array_equal(one.bgr, again.bgr) and np.array_equal(one.depth_m, again.depth_m)
    assert np.array_equal(one.depth_m, other.depth_m)
    assert np.abs(one.bgr.astype(int) - other.bgr.astype(int)).mean() > 10


def test_textures_have_fine_structure_and_consistent_mip_levels():
    tex = make_texture("plaster", (256, 512), 0.003, seed=1)
    gray = tex.astype(np.float64).mean(axis=2)
    # Contrast between neighbouring texels (3 mm apart): what correlation needs.
    assert np.abs(np.diff(gray, axis=1)).mean() > 8
    assert np.array_equal(tex, make_texture("plaster", (256, 512), 0.003, seed=1))
    levels = mip_levels(tex, 4)
    assert [lv.shape[:2] for lv in levels] == [(256, 512), (128, 256), (64, 128), (32, 64)]
    # Level 1 texel (i, j) is the mean of level-0 texels 2i..2i+1, 2j..2j+1.
    block = tex[:2, :2].astype(np.float64).mean(axis=(0, 1))
    assert np.abs(levels[1][0, 0] - block).max() <= 1


def test_surfaces_seen_from_behind_are_culled():
    scene = plane_scene(distance_m=2.0, size_m=6.0)
    renderer = Renderer(scene, INTR, texel_m=0.02)
    # Behind the wall (x > 2), looking back at it along -x: only its back.
    R_W_C = Rotation.from_euler("z", 180.0, degrees=True).as_matrix() @ R_B_C
    out = renderer.render(R_W_C, np.array([3.0, 0.0, 0.0]), with_ids=True)
    assert (out.depth_m == 0).all() and (out.surface_id == -1).all()
