"""The axial part of NI-SLAM's motion (t_z, Eq. 18; docs/nislam-error-budget.md,
"The axial part, split"): the depth gate scaled with the sensor noise, every
cell in far sparse views, the key refinement (Eq. 19, kernels.refine_key)
carried to the sub-cell peak and gated, and a cell's depth from its front
surface's mean (kernels.zbuffer_project)."""

from __future__ import annotations

import numpy as np
import pytest

from onboard.nislam import kernels as kern

H, W = 40, 50
GX, GY = 0.01, 0.005  # key depth slope [m per cell]: a surface seen at a slant


def plane(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return 2.0 + GX * u + GY * v


def frame(du: int, dv: int, fu: float, fv: float, tz: float) -> np.ndarray:
    """The plane seen after a shift by (du + fu, dv + fv) cells and t_z along
    the key's axis, as the current frame's projection holds it."""
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    return (plane(uu - du - fu, vv - dv - fv) - tz).astype(np.float32)


def key() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    return (np.full((H, W), 0.5, np.float32), plane(uu, vv).astype(np.float32),
            np.ones((H, W), np.float32))


def refine(ref, cur, shift, tz, carry: bool = True, gate: float = 0.1) -> int:
    du, dv, fu, fv = shift
    ones = np.ones((H, W), np.float32)
    return kern.refine_key(*ref, ones * 0.5, cur, ones, du, dv, fu if carry else 0.0,
                           fv if carry else 0.0, tz, gate)


def tz_against(ref, cur, shift) -> float:
    du, dv, fu, fv = shift
    ones = np.ones((H, W), np.float32)
    sums = kern.depth_difference_sums(ref[1], ones, ref[0], cur, ones, ones * 0.5, du, dv, 0.1,
                                      0.1, 0.01, 1, fu, fv, 0.0015, 0.001, True, 1)
    return -float(sums[kern.SUM_D] / sums[kern.SUM_W])


A = (3, -2, 0.4, -0.35)  # the refining frame's shift: whole and sub-cell parts
B = (5, 1, -0.3, 0.2)  # the next frame's


def test_refined_key_stays_on_the_surface() -> None:
    """Averaged in at the whole-cell shift the frame's depth is the surface
    (fu, fv) cells away: the key's depth moves by half of -(fu GX + fv GY)
    after one frame; carried along the slope it stays exact."""
    ref = key()
    n = refine(ref, frame(*A, 0.03), A, 0.03)
    inner = np.s_[3:-3, 6:-6]
    assert n > 0.7 * H * W
    assert np.abs(ref[1][inner] - key()[1][inner]).max() < 2e-5
    assert (ref[2][inner] == 2.0).all()
    old = key()
    refine(old, frame(*A, 0.03), A, 0.03, carry=False)
    bias = -(A[2] * GX + A[3] * GY) / 2
    assert np.median(old[1][inner] - key()[1][inner]) == pytest.approx(bias, abs=1e-5)


def test_next_frame_t_z_against_the_refined_key_is_exact() -> None:
    """Two frames with known t_z: the second measured against a key refined by
    the first. The old refinement leaves the first frame's rounding times the
    slope in the key, and the second frame's t_z inherits it."""
    tz_a, tz_b = 0.03, -0.02
    ref = key()
    refine(ref, frame(*A, tz_a), A, tz_a)
    assert tz_against(ref, frame(*B, tz_b), B) == pytest.approx(tz_b, abs=2e-5)
    old = key()
    refine(old, frame(*A, tz_a), A, tz_a, carry=False)
    err = tz_against(old, frame(*B, tz_b), B) - tz_b
    assert abs(err) > 1e-3  # ~1.2 mm: half of 0.4 x 10 mm - 0.35 x 5 mm, on every cell


def test_other_surface_does_not_enter_the_key() -> None:
    """Cells where the frame sees another surface (behind an occluding edge,
    0.5 m away) are left as they were, count included; Eq. 18's gate would
    reject them, and averaged in they would move the key's depth there by
    25 cm."""
    ref = key()
    cur = frame(*A, 0.0)
    cur[10:20, 10:30] += 0.5
    refine(ref, cur, A, 0.0)
    ks = np.s_[10 - A[1]:20 - A[1], 10 - A[0]:30 - A[0]]  # key cells of that patch
    assert np.abs(ref[1][ks] - key()[1][ks]).max() < 1e-6
    assert (ref[2][ks] == 1.0).all()
    # A key cell that was empty takes the frame's depth as it is.
    empty = key()
    empty[2][5, 5] = 0.0
    refine(empty, cur, A, 0.0)
    assert empty[2][5, 5] == 1.0
    assert empty[1][5, 5] == pytest.approx(cur[5 + A[1], 5 + A[0]], abs=1e-6)


def _view(z_m: float, seed: int, tz: float):
    """A wall at z_m metres, 200 x 260 cells, a fifth of them holding a
    point (a far, sparse view), seen twice with the sensor noise
    0.0015 z^2 drawn anew (key, then a frame moved t_z towards it)."""
    from types import SimpleNamespace

    from onboard.nislam.projection import AxonometricImage

    rng = np.random.default_rng(seed)
    shape = (200, 260)
    sd = 0.0015 * z_m * z_m
    km = (rng.random(shape) < 0.2).astype(np.float32)
    cm = (rng.random(shape) < 0.2).astype(np.float32)
    gray = np.full(shape, 0.5, np.float32)
    kd = ((z_m + rng.normal(0.0, sd, shape)) * km).astype(np.float32)
    cd = ((z_m - tz + rng.normal(0.0, sd, shape)) * cm).astype(np.float32)
    key = SimpleNamespace(match_depth=kd, mask0=km, match_gray=gray,
                          img=SimpleNamespace(res_m=0.01))
    return key, AxonometricImage(gray, cd, cm, 0.01)


def _tz_errors(z_m: float, **params) -> tuple[np.ndarray, np.ndarray]:
    """t_z errors over 24 noise draws, and the matched cells, with `params`."""
    import dataclasses

    from onboard.nislam.depth import depth_translation
    from onboard.nislam.params import NislamParams

    p = dataclasses.replace(NislamParams(), **{"min_matched_cells": 50, "depth_gate_sigmas": 0.0,
                                               "depth_all_cells_sd_m": 0.0, **params})
    fits = [depth_translation(*_view(z_m, seed, 0.02), 0, 0, p) for seed in range(24)]
    return np.array([f.tz_m - 0.02 for f in fits]), np.array([f.matched for f in fits])


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(e))))


def test_far_view_depth_gate_scales_with_the_noise() -> None:
    """At 5 m a difference of two depths errs by 52 mm: the fixed 0.1 m gate
    around the median of ~130 sampled cells cuts it at 2 sigma about that
    median's own error (~6 mm), and t_z follows the median (2.3 mm RMS
    here against 1.1 mm for the plain mean of every matched cell). Widened
    to 4 sigma of each difference's noise, the cut is about the truth."""
    fixed, _ = _tz_errors(5.0)
    scaled, _ = _tz_errors(5.0, depth_gate_sigmas=4.0)
    assert _rms(fixed) > 1.8e-3
    assert _rms(scaled) < 0.7 * _rms(fixed)
    # A near view (1 m: 2 mm) keeps the fixed gate: the same cells, the same t_z.
    near_fixed, n_fixed = _tz_errors(1.0)
    near_scaled, n_scaled = _tz_errors(1.0, depth_gate_sigmas=4.0)
    assert (n_fixed == n_scaled).all()
    assert np.allclose(near_fixed, near_scaled, atol=1e-9)


def test_far_sparse_view_takes_every_cell() -> None:
    """At 5 m every other row and column leaves t_z uncertain by more than
    depth_all_cells_sd_m (sensor noise alone, from the weights' sum): then
    every cell is summed; a near view keeps to the sampled cells."""
    _, sampled = _tz_errors(5.0, depth_gate_sigmas=4.0)
    every, matched = _tz_errors(5.0, depth_gate_sigmas=4.0, depth_all_cells_sd_m=0.0003)
    assert (matched > 3 * sampled).all()
    assert _rms(every) < _rms(_tz_errors(5.0, depth_gate_sigmas=4.0)[0])
    _, near = _tz_errors(1.0, depth_all_cells_sd_m=0.0003)
    _, near_sampled = _tz_errors(1.0)
    assert (near == near_sampled).all()


def test_front_surface_mean_is_not_biased_toward_the_camera() -> None:
    """Eight noisy points of one surface (2 m, 10 mm noise) and one of a
    surface behind (2.5 m) fall in one cell: the nearest point errs by
    sigma E[min of 8 normals] (-14 mm); the front surface's mean (points
    within 2 cm + 3 x 0.0015 z^2 of the nearest) by the noise over sqrt(8)."""
    rng = np.random.default_rng(3)
    near, far = [], []
    for _ in range(200):
        z = np.append(2.0 + rng.normal(0.0, 0.01, 8), 2.5).astype(np.float32)[None, :]
        rays = np.zeros((1, 9, 3), np.float32)
        rays[..., 2] = 1.0
        m = np.array([[1.0, 0, 0, 0.5], [0, 1.0, 0, 0.5], [0, 0, 1.0, 0]], np.float32)
        gray = np.zeros((1, 9), np.uint8)
        near.append(kern.zbuffer_project(z, gray, rays, m, 1, 1, False)[0][0, 0] - 2.0)
        far.append(kern.zbuffer_project(z, gray, rays, m, 1, 1, False, 0.02, 0.0045)[0][0, 0] - 2.0)
    assert np.mean(near) < -0.012
    assert abs(np.mean(far)) < 0.002
    assert np.std(far) < 0.006  # ~10 mm / sqrt(8), the far surface left out
