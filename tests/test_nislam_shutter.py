"""Rolling-shutter correction of the NI-SLAM cloud (onboard/nislam/shutter.py)."""

import numpy as np
from scipy.spatial.transform import Rotation

from onboard.core.camera import CameraIntrinsics
from onboard.nislam.projection import make_cloud
from onboard.nislam.shutter import rolling_shutter_cloud

INTR = CameraIntrinsics(fx=520.0, fy=520.0, cx=319.5, cy=239.5, width=640, height=480)


def _cloud(stride=2):
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.8, 3.0, (480, 640)).astype(np.float32)
    bgr = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
    return make_cloud(bgr, depth, INTR, 0.2, 6.0, stride)


def _points(c):
    return c.rays * c.depth_m[..., None]


def test_each_row_is_rotated_to_the_middle_rows_instant():
    c = _cloud()
    w = np.radians([40.0, -65.0, 25.0])  # body rate, rad/s: fr1/rpy's rates
    readout = 0.03
    out = rolling_shutter_cloud(c, w, readout, INTR.height, 2)
    rows = c.depth_m.shape[0]
    tau = readout * (np.arange(rows) * 2 / INTR.height - 0.5)
    exact = np.stack([Rotation.from_rotvec(w * t).apply(_points(c)[i]) for i, t in enumerate(tau)])
    got = _points(out)
    # First order in an angle of at most 1.2 deg (80 deg/s for 15 ms): the
    # second-order rest is ~1 % of what the correction moves; a wrong sign or
    # row order would leave 100-200 %.
    moved = np.abs(exact - _points(c)).max()
    assert moved > 0.05
    assert np.abs(got - exact).max() < 0.02 * moved
    assert np.allclose(out.rays[..., 2], 1.0)
    # The middle row is the reference: untouched.
    mid = rows // 2
    assert np.allclose(got[mid], _points(c)[mid], atol=1e-6)


def test_no_rate_or_no_readout_changes_nothing():
    c = _cloud()
    for w, readout in ((np.zeros(3), 0.03), (np.radians([50.0, 10.0, 0.0]), 0.0)):
        out = rolling_shutter_cloud(c, w, readout, INTR.height, 2)
        assert np.allclose(_points(out), _points(c), atol=1e-6)
