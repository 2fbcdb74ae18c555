"""Small typed messages shared by sources, trackers and outputs.

Conventions (see README "Frames"): camera optical frame C (x right, y down,
z forward); transforms named R_<to>_<from>; quaternions carry their order in
the name (`q_xyzw` as TUM/scipy, `q_wxyz` as MAVLink).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of an undistorted image, in pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


@dataclass(frozen=True)
class RgbdFrame:
    """One colour + registered depth pair, already undistorted.

    `bgr`: (H, W, 3) uint8 in OpenCV channel order; `depth_m`: (H, W) float32
    metres with 0 = no measurement; `t_s`: capture time on the source's clock.
    """

    t_s: float
    bgr: np.ndarray
    depth_m: np.ndarray


class AttitudeSource(Protocol):
    """Where a tracker asks for the camera's orientation at a capture time."""

    def rotation_at(self, t_s: float) -> np.ndarray | None:
        """R_W_C (3x3, camera optical to attitude world) at `t_s`, or None when
        no trustworthy attitude covers that time."""
        ...
