"""Which pixels a frame's cloud takes: its pixel step and the cloud itself.

NI-SLAM projects the whole organised cloud onto a 480 x 360 grid (the
authors' code took every pixel); `pixel_stride = 2` takes every 2nd pixel in
each direction, a quarter of the work, which fills about one cell per point
where the points land at most a cell apart (1.5 m at the usual cell size).
Further away they land further apart than the grid's cells, and most cells
stay empty: Eq. 18 then compares only the few filled in both images and the
correlation peak is found on a sparse image (docs/nislam-error-budget.md,
"Sampling"). `max_point_spacing_cells` > 0 gives such a key (and the frames
matched against it) a finer step.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from onboard.core.camera import CameraIntrinsics
from onboard.core.messages import AttitudeSource, RgbdFrame
from onboard.nislam.calibration import body_rate
from onboard.nislam.params import NislamParams
from onboard.nislam.projection import Cloud, make_cloud
from onboard.nislam.shutter import rolling_shutter_cloud


def frame_cloud(
    frame: RgbdFrame, stride: int, r_cd: np.ndarray | None, intr: CameraIntrinsics,
    p: NislamParams, attitude: AttitudeSource, t_att: float,
) -> Cloud:
    """The frame's cloud at pixel step `stride` (`r_cd`: its depth's rotation
    from its colour's instant, projection.make_cloud)."""
    cloud = make_cloud(frame.bgr, frame.depth_m, intr, p.min_depth_m, p.max_depth_m, stride, r_cd)
    if p.rolling_shutter_readout_s != 0.0:
        # Rows exposed one after another: each brought to the middle row's
        # instant, the one the attitude is looked up at (nislam/shutter.py).
        w = body_rate(attitude, t_att, p.rolling_shutter_rate_half_window_s)
        if w is not None:
            cloud = rolling_shutter_cloud(cloud, w, p.rolling_shutter_readout_s, intr.height, stride)
    return cloud


def median_depth_m(cloud: Cloud) -> float:
    """Median depth of the valid points on every 4th row and column (NaN: none)."""
    z = cloud.depth_m[::4, ::4]
    z = z[z > 0]
    return float(np.median(z)) if z.size else float("nan")


def stride_for_grid(res_m: float, z_m: float, fx_px: float, max_stride: int, spacing_cells: float) -> int:
    """The largest pixel step (at most max_stride) whose points, z_m away,
    land at most spacing_cells cells of res_m apart (stride z / f metres)."""
    if not (spacing_cells > 0 and z_m > 0):
        return max_stride
    return max(1, min(max_stride, int(spacing_cells * fx_px * res_m / z_m)))


def key_cloud(
    cloud: Cloud, remake: Callable[[int], Cloud] | None, res_m: float, fx_px: float, p: NislamParams,
) -> Cloud:
    """The cloud a key of cell size res_m is made from: `cloud`, or the same
    frame at the step stride_for_grid asks for (`remake`). The key keeps that
    step and its frames take it too (Key.stride), so key and frame fill their
    cells alike."""
    want = stride_for_grid(res_m, median_depth_m(cloud), fx_px, p.pixel_stride,
                           p.max_point_spacing_cells)
    if want == cloud.stride or remake is None:
        return cloud
    return remake(want)


def match_cloud(cloud: Cloud, remake: Callable[[int], Cloud] | None, p: NislamParams) -> Cloud:
    """The cloud Eq. 18's key images (and the map's) are projected from: the
    key frame at `key_depth_stride` where that is finer than the key's own
    step (`cloud`), else `cloud`. Its frames keep the key's step."""
    step = p.key_depth_stride
    if step <= 0 or step >= cloud.stride or remake is None:
        return cloud
    return remake(step)
