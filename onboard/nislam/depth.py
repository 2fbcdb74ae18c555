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

    `frac`: the peak's sub-cell part beyond (du, dv). With `depth_subcell`
    (default) each difference is carried to the sub-cell shift along the
    key's depth slope (kernels.depth_difference_sums): at the whole-cell
    shift, a surface seen at a grazing angle (5 cm of depth per cell) moves
    t_z by the rounding times its slope, centimetres from one frame to the
    next. With `depth_sigma_floor_m` > 0 the fit is also weighted by the
    inverse variance of each difference.
    """
    s = key.img.res_m

    def sums_at(step: int) -> np.ndarray:
        return kern.depth_difference_sums(
            key.match_depth, key.mask0, key.match_gray, img.depth_m, img.mask, img.gray, du, dv,
            p.gate_gray, p.gate_depth_m, s, p.min_matched_cells // 16, frac[0], frac[1],
            p.depth_sigma_rel, p.depth_sigma_floor_m, p.depth_subcell, step, p.depth_gate_sigmas,
            p.depth_slope_limited,
        )

    sums = sums_at(p.depth_cell_step)
    if p.depth_cell_step > 1 and p.depth_sigma_floor_m > 0 and p.depth_all_cells_sd_m > 0 \
            and float(sums[kern.SUM_W]) > 0 \
            and 2.0 / float(sums[kern.SUM_W]) > p.depth_all_cells_sd_m ** 2:
        # The sensor noise alone leaves t_z this uncertain on the sampled
        # cells (the inverse of the weights' sum, for the difference of two
        # images): far, sparse views (5 m: 37 mm per point, ~1000 cells),
        # where every cell's own noise is what is left. All cells then.
        sums = sums_at(1)
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
