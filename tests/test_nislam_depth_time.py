"""A frame whose depth was captured at another instant than its colour
(the Kinect: pairs up to 20 ms apart, depth 20 ms before its stamp): the
camera model's depth lag, the reader's depth stamp, and NI-SLAM's geometry
at the depth's attitude, kept with its key (onboard/nislam/tracker.py)."""

import dataclasses
import shutil

import numpy as np
import pytest

from onboard import NislamError
from onboard.core.camera import CameraIntrinsics
from onboard.nislam.params import NislamParams
from onboard.nislam.tracker import NislamTracker
from sim_replay.attitude import AttitudeErrorModel, attitude_for_replay
from sim_replay.tum import open_sequence
from sim_replay.tum_files import load_camera

FR3 = ("fx = 535.4\nfy = 539.2\ncx = 320.1\ncy = 247.6\nwidth = 640\nheight = 480\n"
       "depth_scale = 5000.0\n")


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


def test_a_key_made_from_a_frame_keeps_its_geometrys_attitude(shared_data):
    """The geometry is rotated with the attitude at the depth's instant, every
    other look-up stays at the colour's: the key keeps the rotation between
    the two (`r_geom`), so its attitude looked up again at its colour instant
    and turned by it is the one its cloud was projected with. And the
    compensation is in effect: the poses differ from tracking the depth as
    if captured with the colour."""
    seq = open_sequence(shared_data / "fixtures" / "tum_fr1_desk_9frames")
    attitude, _ = attitude_for_replay(seq, AttitudeErrorModel())
    # From the second frame: the first one's depth instant precedes the first
    # attitude sample (then it is taken as if captured with its colour).
    frames = list(seq.frames())[1:]
    assert all(abs(f.depth_t_s - f.t_s) > 1e-3 for f in frames)  # the Kinect's pairs and lag

    def run(params):
        tracker = NislamTracker(seq.intrinsics, params)
        out = []
        for f in frames:
            out.append(tracker.track(f, attitude))
            tracker.finish_frame()
        return tracker, out

    params = NislamParams(rolling_shutter_readout_s=0.0, calibrate_time_offset=False)
    tracker, results = run(params)
    assert all(r.trusted for r in results)
    key = tracker._key
    first = frames[0]  # the first key is made from the first frame tracked
    assert key is not None and key.t_s == first.t_s and key.r_geom is not None
    at_depth = attitude.rotation_at(first.depth_t_s)
    assert np.allclose(key.R_W_C, at_depth, atol=1e-9)
    assert np.allclose(attitude.rotation_at(key.t_s) @ key.r_geom, at_depth, atol=1e-9)
    assert not np.allclose(key.r_geom, np.eye(3), atol=1e-4)  # it did turn
    _, as_colour = run(dataclasses.replace(params, depth_time_compensation=False))
    moved = max(float(np.linalg.norm(a.p_W_m - b.p_W_m)) for a, b in zip(results, as_colour,
                                                                          strict=True))
    assert moved > 1e-4
