"""Rolling-shutter correction of a frame's cloud (NI-SLAM Sec. IV-A input).

A rolling-shutter colour camera (the Kinect's, the OAK-D's IMX378) exposes
its rows one after another over the readout time; the cloud is built on the
colour image's rays (registered depth only scales them), so under rotation
each row of the cloud was seen from a slightly different attitude. NI-SLAM
rotates the whole cloud by one attitude (R_rel of Sec. IV-A1): the rows are
then sheared and stretched against the key by omega x (row time), in
proportion to depth like any attitude error, and the correlation peak (Eq.
15) moves with where the texture sits in the image. On `tum_fr1_rpy`
(65 deg/s median) this was the largest single source of the lateral error
against the key (docs/nislam-error-budget.md).

Each row is brought to the frame's reference instant (its middle row, the
instant the attitude is looked up at): p_ref = exp([omega] tau_v) p_row with
tau_v = readout (v / H - 1/2) and omega the body rate, to first order
p + tau_v omega x p (0.5 deg at most at 65 deg/s and 30 ms). Pure: arrays in,
a new Cloud out.
"""

from __future__ import annotations

import numpy as np

from onboard.nislam.kernels import shutter_rays
from onboard.nislam.projection import Cloud


def rolling_shutter_cloud(
    cloud: Cloud, omega_rad_s: np.ndarray, readout_s: float, height_px: int, stride: int
) -> Cloud:
    """`cloud` with each row rotated to the middle row's instant.

    `omega_rad_s`: the body rate in camera axes; `readout_s`: time from the
    first to the last row (top row first); `height_px`, `stride`: the image
    height and the cloud's row step, which place each cloud row in time.
    The rays stay at unit depth (x/z, y/z, 1) and the depth takes the rotated
    z, as projection.make_cloud's consumers expect."""
    rows = cloud.depth_m.shape[0]
    tau = (readout_s * (np.arange(rows, dtype=np.float32) * stride / height_px - 0.5)).astype(
        np.float32)
    w = np.asarray(omega_rad_s, np.float32)
    rays, depth = shutter_rays(cloud.rays, cloud.depth_m, tau, w[0], w[1], w[2])
    return Cloud(depth, cloud.bgr, cloud.gray8, rays, cloud.stride)
