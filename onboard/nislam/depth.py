"""Depth translation of NI-SLAM (Eq. 18): the camera's motion along the key's
optical axis from the depth differences of well-matched cells, with the tilt of
those differences (the residual rotation the depth image shows).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from onboard.nislam import kernels as kern
from onboard.nislam.keys import Key
from onboard.nislam.params import NislamParams
from onboard.nislam.projection import AxonometricImage


@dataclass(frozen=True)
class DepthFit:
    """Result of the depth step (Eq. 18 and the tilt of the differences)."""

    tz_m: float  # camera translation along the key's optical axis
    theta_rad: np.ndarray  # tilt of the depth differences as a rotation (x, y, 0)
    z_mean_m: float  # mean key depth of the matched cells
    matched: int  # matched cells (every other row and column)
    var_z_m2: float  # scatter of the depth differences over the matched cells
    shift_fix_cells: tuple[float, float] = (0.0, 0.0)  # registration error the depth showed (du, dv)


def depth_translation(
    key: Key, img: AxonometricImage, du: int, dv: int, p: NislamParams,
    frac: tuple[float, float] = (0.0, 0.0),
) -> DepthFit | None:
    """Eq. 18 with robust gating, plus the residual tilt.

    Delta = D~ - D_key over cells seen in both whose gray agrees (T_c); the
    depth gate is centred on the median rather than the previous t_z, which
    lets fast z motion reject every cell (ref. pitfalls). Under a residual
    rotation theta the differences form a plane,
    Delta = -t_z - theta_x y + theta_y x, fitted in closed form from the
    sums of onboard.nislam.kernels.depth_difference_sums (every other row and
    column: a quarter of the cells fixes three parameters just as well).

    `frac`: the peak's sub-cell part beyond (du, dv). With
    `depth_sigma_floor_m` > 0 the fit is weighted by the inverse variance of
    each difference and the differences are carried to the sub-cell shift
    (kernels.depth_difference_sums): the paper's plain mean lets slanted
    surfaces and depth edges, whose differences move with the rounding of the
    shift, set t_z.
    """
    s = key.img.res_m
    sums = kern.depth_difference_sums(
        key.depth_ref, key.mask0, key.gray_ref, img.depth_m, img.mask, img.gray, du, dv,
        p.gate_gray, p.gate_depth_m, s, p.min_matched_cells // 16, frac[0], frac[1],
        p.depth_sigma_rel, p.depth_sigma_floor_m, p.depth_subcell, p.depth_cell_step,
    )
    if float(sums[kern.N]) < p.min_matched_cells:
        return None
    n_cells = int(sums[kern.N])
    n = float(sums[kern.SUM_W])  # the weights' sum: the count when unweighted
    if not n > 0.0:
        return None
    sum_d = float(sums[kern.SUM_D])
    z_mean = float(sums[kern.SUM_ZKEY]) / n
    # The authors' sigma_z^2 (ref. §10): scatter of Delta around its mean.
    var_z = max(float(sums[kern.SUM_DD]) / n - (sum_d / n) ** 2, 0.0)
    theta = np.zeros(3)

    def fit(tz: float) -> DepthFit:
        return DepthFit(float(tz), theta, z_mean, n_cells, var_z)

    if p.depth_registration_sigma_cells > 0.0 and (p.depth_subcell or p.depth_sigma_floor_m > 0.0):
        return _joint_fit(sums, n, n_cells, z_mean, var_z, p)
    if not p.depth_tilt_fit:
        return fit(-sum_d / n)
    # Normal equations of Delta ~ a + b (x - mx) + c (y - my), centred on
    # the matched cells so a (their mean) stays well determined even when
    # the overlap is a thin strip far from the axis.
    mx, my = float(sums[kern.SUM_X]) / n, float(sums[kern.SUM_Y]) / n
    sxy = float(sums[kern.SUM_XY]) - n * mx * my
    ata = np.array([
        [float(sums[kern.SUM_XX]) - n * mx * mx, sxy],
        [sxy, float(sums[kern.SUM_YY]) - n * my * my],
    ])
    atb = np.array([float(sums[kern.SUM_DX]) - mx * sum_d, float(sums[kern.SUM_DY]) - my * sum_d])
    try:
        b, c = np.linalg.solve(ata, atb)
    except np.linalg.LinAlgError:
        return fit(-sum_d / n)
    lim = p.depth_tilt_max_rad
    theta[0] = np.clip(-c, -lim, lim)
    theta[1] = np.clip(b, -lim, lim)
    # -t_z is the plane's value on the key's optical axis (x = y = 0); the
    # clipped tilt bounds how far a poor fit can move it from the mean.
    tz = -sum_d / n + theta[1] * mx - theta[0] * my
    return fit(tz)


def _joint_fit(sums: np.ndarray, n: float, n_cells: int, z_mean: float, var_z: float,
               p: NislamParams) -> DepthFit:
    """t_z and the peak's registration error delta (cells) together.

    Carried to the sub-cell peak, each difference still reads
    Delta_i = -t_z - g_i . delta, g_i the key's depth slope (m per cell):
    the peak's error is common to every cell, so it does not average out, and
    on a surface seen at a grazing angle (5 cm of depth per 9 mm cell on the
    synthetic flights) 0.2 cell of it is 1 cm of t_z. Least squares in
    (a = -t_z, b = -delta), delta with a prior of `depth_registration_sigma_cells`
    (the peak's own precision, docs/nislam-error-budget.md): where the
    matched surfaces slope in different directions the depth pins delta and
    t_z no longer pays for it; on one plane delta along its slope stays with
    the prior. The prior's weight is in the fit's units: the weights are
    inverse variances (m^-2) when weighted, else 1 per cell against the
    differences' own scatter.
    """
    unit = 1.0 if p.depth_sigma_floor_m > 0.0 else 1.0 / max(var_z, 1e-8)
    lam = 1.0 / (unit * p.depth_registration_sigma_cells**2)
    ata = np.array([
        [n, sums[kern.SUM_GX], sums[kern.SUM_GY]],
        [sums[kern.SUM_GX], sums[kern.SUM_GXX] + lam, sums[kern.SUM_GXY]],
        [sums[kern.SUM_GY], sums[kern.SUM_GXY], sums[kern.SUM_GYY] + lam],
    ])
    atb = np.array([sums[kern.SUM_D], sums[kern.SUM_DGX], sums[kern.SUM_DGY]])
    try:
        a, bx, by = np.linalg.solve(ata, atb)
    except np.linalg.LinAlgError:
        a, bx, by = float(sums[kern.SUM_D]) / n, 0.0, 0.0
    fix = (-float(bx), -float(by)) if p.depth_refines_shift else (0.0, 0.0)
    return DepthFit(-float(a), np.zeros(3), z_mean, n_cells, var_z, fix)
