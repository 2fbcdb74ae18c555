"""A frame whose depth was captured at another instant than its colour
(the Kinect: pairs up to 20 ms apart, depth 20 ms before its stamp): the
camera model's depth lag, the reader's depth stamp, and NI-SLAM's geometry
rotated by the body rate over the gap (onboard/nislam/tracker.py)."""

import dataclasses
import shutil

import cv2
import numpy as np
import pytest

from onboard import NislamError
from onboard.core.camera import CameraIntrinsics
from onboard.core.rotations import so3_exp, so3_log
from onboard.nislam.params import NislamParams
from onboard.nislam.tracker import NislamTracker
from sim_replay.attitude import AttitudeErrorModel, attitude_for_replay
from sim_replay.tum import open_sequence
from sim_replay.tum_files import load_camera

FR3 = "fx = 535.4\nfy = 539.2\ncx = 320.1\ncy = 247.6\nwidth = 640\nheight = 480\ndepth_scale = 5000.0\n"


def test_so3_exp_is_rodrigues_and_inverts_so3_log():
    for w in (np.array([0.3, -0.2, 0.1]), np.array([1e-12, 0.0, 0.0]), np.array([0.0, 2.0, 0.0])):
        assert np.allclose(so3_exp(w), cv2.Rodrigues(w)[0], atol=1e-12)
        assert np.allclose(so3_log(so3_exp(w)), w, atol=1e-9)


def test_tum_cameras_capture_depth_before_its_stamp(tmp_path, shared_data):
    fr1 = tmp_path / "rgbd_dataset_freiburg1_rpy"
    fr1.mkdir()
    assert load_camera(fr1).depth_lag_s == -0.020
    own = tmp_path / "own"
    own.mkdir()
    (own / "camera.toml").write_text(FR3)
    assert load_camera(own).depth_lag_s == 0.0  # a camera.toml without it: stamps as recorded
    (own / "camera.toml").write_text(FR3 + "depth_lag_s = 0.5\n")
    with pytest.raises(NislamError, match="depth_lag_s"):
        load_camera(own)

    # The reader moves each depth stamp by the lag, nothing else.
    src = shared_data / "fixtures" / "tum_fr3_office_16frames"
    copy = tmp_path / "office"
    shutil.copytree(src, copy)
    (copy / "camera.toml").write_text(FR3 + "depth_lag_s = 0.0\n")
    kinect = list(open_sequence(src).frames())
    as_stamped = list(open_sequence(copy).frames())
    assert len(kinect) == len(as_stamped) == 16
    for a, b in zip(kinect, as_stamped, strict=True):
        assert a.t_s == b.t_s
        assert a.depth_t_s == pytest.approx(b.depth_t_s - 0.020, abs=1e-9)
        assert np.array_equal(a.depth_m, b.depth_m)


def test_nislam_takes_the_cameras_readout():
    intr = CameraIntrinsics(500.0, 500.0, 320.0, 240.0, 640, 480, 0.028)
    assert NislamTracker(intr).p.rolling_shutter_readout_s == 0.028
    off = NislamParams(rolling_shutter_readout_s=0.0)
    assert NislamTracker(intr, off).p.rolling_shutter_readout_s == 0.0


class _Recording:
    """An AttitudeSource that notes every instant it is asked for."""

    def __init__(self, base):
        self.base = base
        self.asked: list[float] = []

    def rotation_at(self, t_s):
        self.asked.append(t_s)
        return self.base.rotation_at(t_s)


def test_depth_instant_rotation_comes_from_the_rate_not_a_second_lookup(shared_data):
    """The geometry's attitude is the colour's times exp(omega dt): a second
    look-up at the depth's instant would carry a noisy AHRS's jitter whole
    (1 deg white: ~1.4 deg between the two) into the rotation between them.
    And the compensation is in effect: the poses differ from tracking the
    depth as if captured with the colour."""
    seq = open_sequence(shared_data / "fixtures" / "tum_fr1_desk_9frames")
    attitude, _ = attitude_for_replay(seq, AttitudeErrorModel())
    frames = list(seq.frames())
    assert all(abs(f.depth_t_s - f.t_s) > 1e-3 for f in frames)  # the Kinect's pairs and lag

    def run(params):
        tracker = NislamTracker(seq.intrinsics, params)
        rec = _Recording(attitude)
        out = []
        for f in frames:
            out.append(tracker.track(f, rec))
            tracker.finish_frame()
        return out, rec.asked

    params = NislamParams(rolling_shutter_readout_s=0.0)  # the depth's instant alone
    results, asked = run(params)
    assert all(r.trusted for r in results)
    for f, r in zip(frames, results, strict=True):
        depth_instant = f.depth_t_s + r.attitude_offset_s
        assert min(abs(t - depth_instant) for t in asked) > 1e-6
    as_colour, _ = run(dataclasses.replace(params, depth_time_compensation=False))
    moved = max(float(np.linalg.norm(a.p_W_m - b.p_W_m)) for a, b in zip(results, as_colour,
                                                                          strict=True))
    assert moved > 1e-4
