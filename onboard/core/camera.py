"""The camera: pinhole intrinsics of undistorted images, the recorded camera model
(intrinsics, OpenCV distortion, depth scale, mount) and its undistortion maps.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from onboard.core.rotations import IDENTITY_Q_XYZW


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of an undistorted image, in pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    readout_s: float = 0.0  # rolling shutter: rows read out over this time, top first; 0: global


@dataclass(frozen=True)
class CameraModel:
    """The camera as recorded: pinhole + OpenCV distortion, depth scale and mount.

    `depth_scale`: depth PNG units per metre (TUM 5000, millimetre sensors 1000,
    0 = no depth). `distortion`: OpenCV k1 k2 p1 p2 k3 (empty = none).
    `q_B_C_xyzw`: camera-optical-to-body rotation. `readout_s`: a rolling
    shutter's time from the first row to the last (0: global shutter).
    `depth_lag_s`: when the depth image was captured against its stamp
    (negative: before it); a reader adds it to `RgbdFrame.depth_t_s`.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    depth_scale: float = 5000.0
    distortion: tuple[float, ...] = ()
    q_B_C_xyzw: tuple[float, float, float, float] = IDENTITY_Q_XYZW
    readout_s: float = 0.0
    depth_lag_s: float = 0.0

    def intrinsics(self) -> CameraIntrinsics:
        return CameraIntrinsics(self.fx, self.fy, self.cx, self.cy, self.width, self.height,
                                self.readout_s)

    def k_matrix(self) -> np.ndarray:
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    @property
    def is_distorted(self) -> bool:
        return any(c != 0.0 for c in self.distortion)


@dataclass
class UndistortMaps:
    """Precomputed remap tables (built once per sequence)."""

    # Fixed-point maps make the bilinear colour remap about twice as fast.
    color_map1: np.ndarray
    color_map2: np.ndarray
    # Float maps for depth: nearest lookup on them rounds to the closest source
    # pixel, while the fixed-point integer part would floor (half-pixel bias).
    depth_map_x: np.ndarray
    depth_map_y: np.ndarray


def undistort_maps(camera: CameraModel) -> UndistortMaps:
    k = camera.k_matrix()
    dist = np.asarray(camera.distortion, dtype=np.float64)
    size = (camera.width, camera.height)
    c1, c2 = cv2.initUndistortRectifyMap(k, dist, None, k, size, cv2.CV_16SC2)
    dx, dy = cv2.initUndistortRectifyMap(k, dist, None, k, size, cv2.CV_32FC1)
    return UndistortMaps(c1, c2, dx, dy)
