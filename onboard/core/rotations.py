"""Small SO(3) helpers for the per-frame path, where building scipy Rotation
objects costs more than the maths."""

from __future__ import annotations

import math

import numpy as np


def so3_log(r: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, rad) of a rotation matrix.

    Accurate for angles well below pi, which is all the per-frame code needs
    (rotations between nearby attitude samples).
    """
    cos_a = max(-1.0, min(1.0, 0.5 * (float(r[0, 0] + r[1, 1] + r[2, 2]) - 1.0)))
    angle = math.acos(cos_a)
    skew = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    sin_a = math.sin(angle)
    if sin_a < 1e-9:
        return 0.5 * skew  # first order: R ~ I + [w]x
    return skew * (0.5 * angle / sin_a)
