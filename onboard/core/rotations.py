"""Rotations: SO(3) helpers for the per-frame path (where building scipy
Rotation objects costs more than the maths), xyzw quaternions, and the
camera mount presets R_B_C.

Conventions (docs/frames.md): transforms are named R_<to>_<from>;
quaternions carry their order in the name (`q_xyzw` as TUM and scipy,
`q_wxyz` as MAVLink).
"""

from __future__ import annotations

import math

import numpy as np

from onboard import NislamError


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


Quat = tuple[float, float, float, float]


IDENTITY_Q_XYZW: Quat = (0.0, 0.0, 0.0, 1.0)


# Camera mount presets R_B_C (camera optical -> body FRD), see design.md:
# forward: camera z = body x, camera x = body y, camera y = body z.
# down: camera z = body z, image top towards the nose (camera -y = body x).
MOUNT_R_B_C: dict[str, np.ndarray] = {
    "forward": np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
    "down": np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
}


# R_NED_ENU: East-North-Up world axes into North-East-Down.
R_NED_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def quat_mul(a: Quat, b: Quat) -> Quat:
    """Hamilton product a*b of xyzw quaternions (rotation b first, then a)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def quat_conj(q: Quat) -> Quat:
    return (-q[0], -q[1], -q[2], q[3])


def quat_normalized(q) -> Quat | None:
    """Unit xyzw quaternion, or None if non-finite or (near) zero."""
    x, y, z, w = (float(c) for c in q)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(n) or n < 1e-6:
        return None
    return (x / n, y / n, z / n, w / n)


def quat_slerp(q0: Quat, q1: Quat, w: float) -> Quat:
    x0, y0, z0, w0 = q0
    x1, y1, z1, w1 = q1
    dot = x0 * x1 + y0 * y1 + z0 * z1 + w0 * w1
    if dot < 0.0:  # q and -q are one rotation: take the short way
        x1, y1, z1, w1, dot = -x1, -y1, -z1, -w1, -dot
    if dot > 0.9999995:  # under ~0.1 deg apart: normalised lerp is exact enough
        a, b = 1.0 - w, w
    else:
        theta = math.acos(dot)
        s = math.sin(theta)
        a, b = math.sin((1.0 - w) * theta) / s, math.sin(w * theta) / s
    q = (a * x0 + b * x1, a * y0 + b * y1, a * z0 + b * z1, a * w0 + b * w1)
    n = math.sqrt(sum(c * c for c in q))
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def quat_to_matrix(q: Quat) -> np.ndarray:
    x, y, z, w = q
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    return np.array(
        [
            [1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy)],
            [2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx)],
            [2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy)],
        ]
    )


def matrix_to_quat(r: np.ndarray) -> Quat:
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(np.asarray(r, dtype=np.float64)).as_quat()
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


def mount_rotation(mount: str, q_B_C_xyzw: Quat = IDENTITY_Q_XYZW) -> np.ndarray:
    """R_B_C for a mount preset ("forward", "down"), or from `q_B_C_xyzw` when
    `mount` is "custom"."""
    if mount in MOUNT_R_B_C:
        return MOUNT_R_B_C[mount].copy()
    if mount != "custom":
        raise NislamError(f"unknown camera mount {mount!r} (known: {', '.join(MOUNT_R_B_C)}, custom)")
    q = quat_normalized(q_B_C_xyzw)
    if q is None:
        raise NislamError(f"camera mount quaternion {tuple(q_B_C_xyzw)} is not a rotation")
    return quat_to_matrix(q)
