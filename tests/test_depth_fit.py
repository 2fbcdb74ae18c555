"""The depth translation (Eq. 18) fitted jointly with the correlation peak's
registration error (onboard.nislam.depth._joint_fit)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from onboard.nislam import kernels as kern
from onboard.nislam.depth import _joint_fit
from onboard.nislam.params import NislamParams


def _surface(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Two slanted faces (a roof ridge along v) and a grazing floor: slopes in
    different directions, so the depth alone pins a lateral misregistration."""
    return 2.0 + 0.02 * np.abs(u - 25.0) + np.where(v > 25.0, 0.05 * (v - 25.0), 0.0)


def test_joint_fit_recovers_t_z_despite_a_peak_error() -> None:
    """The peak is off by (0.15, -0.2) cells: the plain mean of the carried
    differences moves t_z by the slopes times that error (centimetres on the
    grazing part); the joint fit returns t_z and the error itself."""
    h, w, du, dv, fu, fv, tz = 50, 50, 2, 1, 0.3, -0.1, 0.03
    err_u, err_v = 0.15, -0.2
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    kd = _surface(uu, vv).astype(np.float32)
    cd = (_surface(uu - du - fu - err_u, vv - dv - fv - err_v) - tz).astype(np.float32)
    ones = np.ones((h, w), np.float32)
    sums = kern.depth_difference_sums(kd, ones, ones, cd, ones, ones, du, dv, 0.1, 0.1, 0.01, 1,
                                      fu, fv, 0.0, 0.0, True, 1)
    n = float(sums[kern.N])
    plain_tz = -sums[kern.SUM_D] / n
    assert abs(plain_tz - tz) > 0.002
    p = dataclasses.replace(NislamParams(), depth_subcell=True, depth_registration_sigma_cells=0.25,
                            depth_refines_shift=True)
    var_z = max(sums[kern.SUM_DD] / n - (sums[kern.SUM_D] / n) ** 2, 1e-6)
    fit = _joint_fit(sums, n, int(n), 2.0, var_z, p)
    assert fit.tz_m == pytest.approx(tz, abs=5e-4)
    # The fix is the error to add to the peak: (err_u, err_v), to within the
    # prior's pull toward zero and the kinks' linearisation.
    assert fit.shift_fix_cells == pytest.approx((err_u, err_v), abs=0.03)
