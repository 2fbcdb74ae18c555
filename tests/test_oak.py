"""OAK-D driver without a device.

1. Against a stand-in of the depthai objects the driver uses
   (tests/peers/fake_depthai.py): pipeline building, intrinsics, frames,
   the IMU rotation vector, USB loss and reconnect, stop time.
2. With REAL depthai pieces that run without a device: a device-less
   Pipeline(False) whose ThreadedHostNode sources feed a host Sync node and
   an IMU queue, read by the driver's own loop; a host CalibrationHandler.
Never searches for or opens a device (DEPTHAI_PROTOCOL=usb as a guard).
"""

from __future__ import annotations

import datetime
import math
import os
import threading
import time

os.environ["DEPTHAI_PROTOCOL"] = "usb"  # before depthai is imported: no network search

import numpy as np
import pytest
from peers.fake_depthai import API_NAMES, FakeDai, Platform
from scipy.spatial.transform import Rotation

from drivers.oak import (
    DEPTH_SCALE_MM,
    OakDriver,
    OakSession,
    OakSettings,
    camera_from_calibration,
    frame_from_group,
    open_oak,
)
from onboard.core.attitude import AttitudeBuffer
from onboard.core.rotations import R_NED_ENU

WAIT_S = 60.0


def settings(**kw) -> OakSettings:
    """Test settings; the frame timeout is far above any stall of this machine
    unless a test is about it."""
    base = dict(width=64, height=40, fps=30.0, imu=True, imu_rate_hz=100,
                reconnect_min_s=0.05, reconnect_max_s=0.2, frame_timeout_s=WAIT_S, poll_s=0.05)
    base.update(kw)
    return OakSettings(**base)


def real_depthai():
    return pytest.importorskip("depthai")


# --------------------------------------------------------------------------- stand-in


def test_stand_in_mimics_real_depthai_names() -> None:
    """Every name the stand-in offers (the driver's whole depthai surface)
    exists in the installed depthai, so the stand-in cannot drift from it."""
    dai = real_depthai()
    missing = []
    for path in API_NAMES:
        obj = dai
        for part in path.split("."):
            if not hasattr(obj, part):
                missing.append(path)
                break
            obj = getattr(obj, part)
    assert not missing, missing
    # The driver treats device loss as RuntimeError: depthai's XLink errors are ones.
    assert issubclass(dai.XLinkReadError, RuntimeError)


def test_pipeline_is_built_as_depthai_3_wants() -> None:
    fake = FakeDai()
    session = open_oak(fake, settings(width=640, height=400, stereo_preset="ROBOTICS"))
    try:
        dev = fake.devices[0]
        pipe = dev.pipeline
        rgb = pipe.requested[fake.CameraBoardSocket.CAM_A]
        assert rgb.size == (640, 400) and rgb.fps == 30.0 and rgb.undistorted is True
        assert pipe.stereo.preset == fake.node.StereoDepth.PresetMode.ROBOTICS
        assert pipe.sync.threshold == datetime.timedelta(seconds=0.5 / 30.0)
        assert pipe.imu_rate == 100 and session.imu_queue is not None
        # Intrinsics from the calibration at the output size (1920x1080 scaled, cropped).
        cam = session.camera
        assert (cam.width, cam.height, cam.depth_scale) == (640, 400, DEPTH_SCALE_MM)
        assert cam.fx == pytest.approx(1500 * 400 / 1080) and cam.cx == pytest.approx(320.0)
        assert cam.distortion == ()  # undistorted on the device
    finally:
        session.close()
    assert fake.devices[0].closed


def test_bmi_imu_gives_no_rotation_vector_and_rvc4_aligns_with_imagealign() -> None:
    fake = FakeDai(imu_name="BMI270", platform=Platform.RVC4)
    session = open_oak(fake, settings(undistort=False))
    try:
        assert session.imu_queue is None
        assert "aligned" not in fake.devices[0].pipeline.queues  # ImageAlign feeds Sync
        assert session.camera.distortion[:2] == (0.1, -0.05)  # distorted output: coefficients
    finally:
        session.close()


def test_driver_delivers_frames_and_rotation_vector() -> None:
    fake = FakeDai(exposure_ns=8_000_000, capture_latency_ns=30_000_000, imu_yaw_rate=0.5)
    buf = AttitudeBuffer()
    drv = OakDriver(settings(), imu_sink=buf.push, dai_loader=lambda: fake)
    drv.start()
    try:
        cam = drv.wait_camera(WAIT_S)
        assert cam is not None and (cam.width, cam.height) == (64, 40)
        got = drv.take(0, WAIT_S)
        assert got is not None
        seq, frame = got
        assert frame.bgr.shape == (40, 64, 3) and frame.bgr.dtype == np.uint8
        assert frame.depth_m.dtype == np.float32
        n = int(round(frame.depth_m[0, 0] * 1000.0)) - 1000  # the frame counter
        assert np.all(frame.bgr == n % 256)
        # Stamp: capture (30 ms before the host got it) + half the exposure, on
        # our clock, to the microsecond of depthai's timestamps.
        mid_exposure_ns = fake.devices[0].pipeline.captured_ns[n] + fake.exposure_ns // 2
        assert frame.t_s == pytest.approx(mid_exposure_ns * 1e-9, abs=1.5e-6)
        assert frame.t_s < time.monotonic()
        assert drv.take(seq, WAIT_S) is not None  # frames keep coming
        assert buf.wait_for_samples(20, WAIT_S)
        # ENU rotation vector -> NED world: yaw about ENU z (up) is a yaw about
        # NED z (down) the other way round, in axes swapped by R_NED_ENU.
        s = buf.newest()
        yaw = 0.5 * s.t_ns * 1e-9
        r_enu = Rotation.from_euler("z", yaw).as_matrix()
        expected = R_NED_ENU @ r_enu
        got_r = Rotation.from_quat(s.q_W_B_xyzw).as_matrix()
        assert np.allclose(got_r, expected, atol=1e-4)
        assert drv.stats.imu_samples >= 20 and drv.stats.opens == 1
    finally:
        assert drv.stop(10)
    assert fake.devices[0].closed


def test_driver_reconnects_after_usb_loss() -> None:
    fake = FakeDai(fail_opens=2)  # no device on the first two searches
    drv = OakDriver(settings(imu=False), dai_loader=lambda: fake)
    drv.start()
    try:
        seq, _ = drv.take(0, WAIT_S)
        assert drv.stats.open_failures == 2 and drv.stats.opens == 1
        fake.unplug()  # USB loss: depthai closes the queues
        assert drv.counters.wait_for(lambda s: s.disconnects == 1, WAIT_S)
        assert drv.counters.wait_for(lambda s: s.opens == 2, WAIT_S)
        seq, _ = drv.take(seq, WAIT_S)
        assert fake.devices[0].closed and len(fake.devices) == 2
        fake.read_error()  # an XLink read error (RuntimeError) on the running device
        assert drv.counters.wait_for(lambda s: s.disconnects == 2 and s.opens == 3, WAIT_S)
        assert drv.take(seq, WAIT_S) is not None and drv.alive
    finally:
        assert drv.stop(10)


def test_driver_treats_a_silent_device_as_lost() -> None:
    fake = FakeDai()
    drv = OakDriver(settings(imu=False, fps=0.2, frame_timeout_s=0.3), dai_loader=lambda: fake)
    drv.start()  # one frame per 5 s: the 0.3 s frame timeout fires first
    try:
        assert drv.counters.wait_for(lambda s: s.frame_timeouts >= 1 and s.opens >= 2, WAIT_S)
    finally:
        assert drv.stop(10)


def test_depth_of_another_size_is_resized_to_colour() -> None:
    fake = FakeDai(depth_size=(20, 32))
    drv = OakDriver(settings(imu=False), dai_loader=lambda: fake)
    drv.start()
    try:
        _, frame = drv.take(0, WAIT_S)
        assert frame.depth_m.shape == (40, 64)
        assert drv.stats.depth_resized >= 1
    finally:
        assert drv.stop(10)


# --------------------------------------------------------------------------- real depthai


def devless_session_factory(n_frames: int, w: int = 64, h: int = 40):
    """A session from a device-less Pipeline(False): ThreadedHostNode sources
    send ImgFrames (BGR colour, RAW16 depth) stamped on the host clock into a
    host-side Sync node, and IMUData with rotation vectors into an IMU queue."""
    dai = real_depthai()
    sent: dict[str, list] = {"t_ns": [], "imu_t_ns": []}
    credits = threading.Semaphore(1)  # frames the test lets the source send

    class Frames(dai.node.ThreadedHostNode):
        def __init__(self) -> None:
            super().__init__()
            self.rgb = self.createOutput()
            self.depth = self.createOutput()

        def run(self) -> None:
            for i in range(n_frames):
                # One frame per credit: the test takes every frame, however
                # slowly, so none is replaced before it was taken.
                while not credits.acquire(timeout=0.05):
                    if not self.mainLoop():
                        return
                if not self.mainLoop():
                    return
                t_ns = time.monotonic_ns()
                ts = datetime.timedelta(microseconds=t_ns // 1000)
                sent["t_ns"].append(t_ns // 1000 * 1000)
                rgb = dai.ImgFrame()
                rgb.setCvFrame(np.full((h, w, 3), i, np.uint8), dai.ImgFrame.Type.BGR888i)
                rgb.setTimestamp(ts)
                depth = dai.ImgFrame()
                depth.setCvFrame(np.full((h, w), 500 + i, np.uint16), dai.ImgFrame.Type.RAW16)
                depth.setTimestamp(ts)
                self.rgb.send(rgb)
                self.depth.send(depth)

    class Imu(dai.node.ThreadedHostNode):
        def __init__(self) -> None:
            super().__init__()
            self.out = self.createOutput()

        def run(self) -> None:
            for i in range(3 * n_frames):
                if not self.mainLoop():
                    return
                t_ns = time.monotonic_ns()
                packet = dai.IMUPacket()
                rv = packet.rotationVector
                rv.i, rv.j, rv.k, rv.real = 0.0, 0.0, math.sin(0.01 * i), math.cos(0.01 * i)
                stamp = rv.timestamp
                stamp.sec, stamp.nsec = t_ns // 10**9, t_ns % 10**9
                rv.timestamp = stamp
                packet.rotationVector = rv
                data = dai.IMUData()
                data.packets = [packet]
                sent["imu_t_ns"].append(t_ns // 1000 * 1000)
                self.out.send(data)
                time.sleep(0.01)

    def factory(dai_mod, s: OakSettings) -> OakSession:
        pipeline = dai_mod.Pipeline(False)
        frames = pipeline.create(Frames)
        imu = pipeline.create(Imu)
        sync = pipeline.create(dai_mod.node.Sync)
        sync.setRunOnHost(True)
        sync.setSyncThreshold(datetime.timedelta(seconds=0.5 / s.fps))
        frames.rgb.link(sync.inputs["rgb"])
        frames.depth.link(sync.inputs["depth"])
        rgbd_q = sync.out.createOutputQueue(4, False)
        imu_q = imu.out.createOutputQueue(50, False)
        calib = dai_mod.CalibrationHandler()
        calib.setCameraIntrinsics(dai_mod.CameraBoardSocket.CAM_A,
                                  [[100.0, 0.0, 32.0], [0.0, 100.0, 20.0], [0.0, 0.0, 1.0]], w, h)
        camera = camera_from_calibration(dai_mod, calib, s)
        pipeline.start()

        def close() -> None:
            pipeline.stop()
            pipeline.wait()

        return OakSession(rgbd_q, imu_q, camera, close, name="device-less")

    return factory, sent, credits


def test_driver_loop_on_a_real_device_less_pipeline() -> None:
    dai = real_depthai()
    factory, sent, credits = devless_session_factory(n_frames=20)
    buf = AttitudeBuffer()
    s = settings(imu_world="ned", frame_timeout_s=30.0)
    drv = OakDriver(s, imu_sink=buf.push, dai_loader=lambda: dai, session_factory=factory)
    drv.start()
    frames = []
    try:
        cam = drv.wait_camera(WAIT_S)
        assert (cam.fx, cam.cx, cam.width) == (100.0, 32.0, 64)
        seq = 0
        while len(frames) < 5:
            got = drv.take(seq, WAIT_S)
            assert got is not None
            seq, f = got
            frames.append(f)
            credits.release()  # the next frame
        assert buf.wait_for_samples(10, WAIT_S)
    finally:
        assert drv.stop(10)
    # Every frame, in order: none was replaced before it was taken.
    assert [int(f.bgr[0, 0, 0]) for f in frames] == [0, 1, 2, 3, 4]
    assert drv.slot.stats.dropped == 0
    # Real ImgFrame/MessageGroup round trip: colour, depth in mm -> m, stamps.
    for f in frames:
        i = int(f.bgr[0, 0, 0])
        assert f.depth_m[0, 0] == pytest.approx((500 + i) / 1000.0)
        assert int(round(f.t_s * 1e9)) == sent["t_ns"][i]  # our clock, microsecond exact
    imu = buf.samples_after(None)
    assert all(s.t_ns in sent["imu_t_ns"] for s in imu)
    assert drv.stats.imu_samples == len(imu)


def test_frame_conversion_on_real_depthai_messages() -> None:
    dai = real_depthai()
    rgb = dai.ImgFrame()
    rgb.setCvFrame(np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3), dai.ImgFrame.Type.BGR888i)
    rgb.setTimestamp(datetime.timedelta(seconds=12.5))
    depth = dai.ImgFrame()
    depth.setCvFrame(np.full((2, 3), 1500, np.uint16), dai.ImgFrame.Type.RAW16)

    class Group(dict):  # MessageGroup's lookup by name; real groups come from Sync above
        pass

    cam = camera_from_calibration(dai, _calib(dai), OakSettings(width=6, height=4))
    frame, resized = frame_from_group(dai, Group(rgb=rgb, depth=depth), cam)
    assert resized and frame.depth_m.shape == (4, 6) and np.all(frame.depth_m == 1.5)
    assert frame.t_s == 12.5 and frame.bgr[1, 2, 0] == rgb.getCvFrame()[1, 2, 0]


def _calib(dai):
    calib = dai.CalibrationHandler()
    calib.setCameraIntrinsics(dai.CameraBoardSocket.CAM_A,
                              [[1000.0, 0.0, 960.0], [0.0, 1000.0, 540.0], [0.0, 0.0, 1.0]],
                              1920, 1080)
    return calib


def test_intrinsics_from_a_real_calibration_handler() -> None:
    dai = real_depthai()
    cam = camera_from_calibration(dai, _calib(dai), OakSettings(width=640, height=400))
    # depthai scales by the larger ratio and crops (keepAspectRatio): 400/1080.
    assert cam.fx == pytest.approx(1000 * 400 / 1080, rel=1e-6)
    assert cam.cx == pytest.approx(320.0) and cam.cy == pytest.approx(200.0)
    assert cam.depth_scale == 1000.0 and cam.distortion == ()
