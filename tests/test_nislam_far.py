"""Eq. 18's carry to the sub-cell peak at depth edges (kernels._limited_slope,
`[nislam] depth_slope_limited`; docs/nislam-error-budget.md, "Far views").

Each depth difference is carried to the sub-cell shift along the key's slope
(Delta + f . g). Across a depth edge the central difference is half the
jump, not the slope of either surface, so every cell next to an edge is
carried by f times half the jump; on a receding staircase (boxes behind
boxes, a floor's clutter seen from afar) those errors share a sign and t_z
inherits them.
"""

from __future__ import annotations

import numpy as np

from onboard.nislam import kernels as kern

SHAPE = (120, 160)
DU, FU, TZ = 3, 0.4, 0.01


def _staircase_tz_error(limited: bool, seed: int) -> float:
    """t_z error on flat steps 5 cm deeper every 8 cells (3 m away, the
    sensor noise model 0.0015 z^2 in the weights), half the cells filled in
    each image, the frame moved DU + FU cells and TZ toward the surface."""
    rng = np.random.default_rng(seed)
    h, w = SHAPE
    u = np.arange(w, dtype=float)[None, :].repeat(h, 0) + 0.5

    def surface(x: np.ndarray) -> np.ndarray:
        return 3.0 + 0.05 * np.floor(x / 8.0)

    km = (rng.random(SHAPE) < 0.5).astype(np.float32)
    cm = (rng.random(SHAPE) < 0.5).astype(np.float32)
    kd = (surface(u) * km).astype(np.float32)
    cd = ((surface(u - DU - FU) - TZ) * cm).astype(np.float32)
    gray = np.full(SHAPE, 0.5, np.float32)
    s = kern.depth_difference_sums(kd, km, gray, cd, cm, gray, DU, 0, 0.1, 0.1, 0.01, 1, FU, 0.0,
                                   0.0015, 0.001, True, 2, 4.0, limited)
    return -s[kern.SUM_D] / s[kern.SUM_W] - TZ


def test_carry_at_edges_takes_the_surface_slope() -> None:
    central = np.array([_staircase_tz_error(False, seed) for seed in range(4)])
    limited = np.array([_staircase_tz_error(True, seed) for seed in range(4)])
    # Central differences: -1.3 to -1.5 mm (measured); minmod: -0.55 to -0.6,
    # what is left being the cells whose frame point lies across the step.
    assert (central < -1.2e-3).all()
    assert (np.abs(limited) < 0.5 * np.abs(central)).all()


def test_limited_slope_on_a_plane_is_the_plane() -> None:
    # No edge: both one-sided slopes agree, minmod keeps the slope, spread 0.
    depth = (2.0 + 0.01 * np.arange(10, dtype=np.float32))[None, :].repeat(5, 0)
    mask = np.ones_like(depth)
    mask[:, 5] = 0.0  # a hole: the nearest filled cell two away on that side
    g, spread = kern._limited_slope(depth, mask, 2, 4, 0, 1)
    assert abs(g - 0.01) < 1e-6 and spread < 1e-6
    g, spread = kern._limited_slope(depth, mask, 2, 9, 0, 1)  # the grid's edge: one side
    assert abs(g - 0.01) < 1e-6 and spread == 0.0
    # A step of 10 cm after cell 4: the flat side's slope, the jump as spread.
    step = depth.copy()
    step[:, 5:] += 0.1
    g, spread = kern._limited_slope(step, np.ones_like(step), 2, 4, 0, 1)
    assert abs(g - 0.01) < 1e-6 and abs(spread - 0.1) < 1e-5
