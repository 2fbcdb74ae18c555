"""OAK-D: RGB-D frames and the on-board IMU's rotation vector (depthai 3.x).

One device, one pipeline (ref. flight-stack doc §7):
  Camera CAM_A  -> requestOutput((width, height), fps, undistorted) --+--> Sync "rgb"
  Camera CAM_B/C -> StereoDepth (preset) -> depth aligned to colour --+--> Sync "depth"
  IMU ROTATION_VECTOR (BNO08x only) -------------------------------------> IMU queue
RVC2 aligns in StereoDepth (`inputAlignTo` fed the undistorted colour output),
RVC4 with an ImageAlign node. Depth is RAW16 millimetres, 0 = invalid. The
Sync node pairs colour and depth within half a frame period. Intrinsics come
from the device calibration at the output size; frames are undistorted on
the device, so the camera model has no distortion (with `undistort` off it
carries the calibration's coefficients).

Timestamps: depthai's `getTimestamp()` is the host steady clock, i.e.
`time.monotonic()` (verified with depthai 3.12.0): the driver converts it to
integer ns, the same clock every other driver stamps with. A frame's stamp
is the middle of the colour exposure.

`import depthai` happens only inside `import_depthai()`, called by the
driver thread: importing this module never loads depthai, and nothing here
searches for devices unless a driver is started. Device searches broadcast
on the network unless DEPTHAI_PROTOCOL=usb (set it in the service unit for a
USB camera). Tests pass a stand-in module and session factory instead.

USB loss: depthai closes the queues (or raises RuntimeError) when the device
vanishes; no frame for `frame_timeout_s` counts as loss too. The driver then
closes the pipeline and device and reopens with backoff; the camera
re-enumerates with another USB id after boot, so nothing is cached.

Its `device_state` (drivers/device_state.py) says no device (not found, or
lost), silent (open, no frame for `frame_timeout_s`) or streaming. The first
search is short (`FIRST_SEARCH_S`), so a missing camera is told within a
second or two of start; later ones use `search_s`.
"""

from __future__ import annotations

import dataclasses
import datetime
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import cv2
import numpy as np

from drivers.device_state import DeviceState, State
from onboard.core.attitude import AttitudeSample, to_body_sample
from onboard.core.camera import CameraModel
from onboard.core.messages import RgbdFrame
from onboard.core.rotations import IDENTITY_Q_XYZW, Quat, quat_mul
from onboard.core.sources import Backoff, Counters, DriverThread, FrameSlot

log = logging.getLogger(__name__)

DEPTH_SCALE_MM = 1000.0  # StereoDepth RAW16: millimetres per metre
STEREO_PRESETS = ("DEFAULT", "FAST_ACCURACY", "FAST_DENSITY", "HIGH_DETAIL", "ROBOTICS",
                  "DENSITY", "ACCURACY")
IMU_WORLDS = ("enu", "ned")
FIRST_SEARCH_S = 1.0  # a camera plugged in at boot enumerates within this
# q_NED_ENU (xyzw): 180 deg about (x + y)/sqrt(2) maps East-North-Up onto North-East-Down.
_Q_NED_ENU: Quat = (math.sqrt(0.5), math.sqrt(0.5), 0.0, 0.0)


def import_depthai() -> ModuleType:
    import depthai

    return depthai


@dataclass(frozen=True)
class OakSettings:
    """Plain values for one OAK-D (built from the [oak] config section)."""

    device: str = ""  # device id (MxId) or name/IP; "" = the first one found
    width: int = 640
    height: int = 400
    fps: float = 30.0
    mono_width: int = 640
    mono_height: int = 400
    undistort: bool = True
    stereo_preset: str = "DEFAULT"
    q_B_C_xyzw: Quat = IDENTITY_Q_XYZW  # camera mount, written into camera.toml
    imu: bool = False  # stream the rotation vector (BNO08x devices)
    imu_rate_hz: int = 100
    imu_world: str = "enu"  # the rotation vector's world axes (BNO08x: East-North-Up)
    imu_q_B_A_xyzw: Quat = IDENTITY_Q_XYZW  # IMU axes -> body
    search_s: float = 3.0  # device search per attempt
    frame_timeout_s: float = 2.0  # no frame for this long = device lost
    reconnect_min_s: float = 0.5
    reconnect_max_s: float = 5.0
    poll_s: float = 0.1  # queue wait per loop turn (bounds the stop time once running)


@dataclass
class OakSession:
    """One open device: its queues, the camera model and how to close it."""

    rgbd_queue: Any  # dai.MessageQueue of MessageGroup {"rgb", "depth"}
    imu_queue: Any | None  # dai.MessageQueue of IMUData, or None
    camera: CameraModel
    close: Callable[[], None]
    name: str = "oak"


class OakUnavailable(RuntimeError):
    """No device found, or it does not offer what the settings ask for."""


# --------------------------------------------------------------------------- device side


def open_oak(dai: ModuleType, s: OakSettings) -> OakSession:
    """Find and open the device, build and start the pipeline."""
    if s.device:
        found, info = dai.Device.getDeviceById(s.device)
    else:
        found, info = dai.Device.getAnyAvailableDevice(datetime.timedelta(seconds=s.search_s))
    if not found:
        raise OakUnavailable(f"no OAK device {s.device or 'available'}")
    device = dai.Device(info)
    try:
        return _build(dai, device, s)
    except BaseException:
        device.close()
        raise


def _build(dai: ModuleType, device: Any, s: OakSettings) -> OakSession:
    pipeline = dai.Pipeline(device)
    cam = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_A)
    rgb_out = cam.requestOutput((s.width, s.height), fps=s.fps, enableUndistortion=s.undistort)
    left = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_B)
    right = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_C)
    mono = (s.mono_width, s.mono_height)
    stereo = pipeline.create(dai.node.StereoDepth).build(
        left.requestOutput(mono, fps=s.fps), right.requestOutput(mono, fps=s.fps),
        presetMode=getattr(dai.node.StereoDepth.PresetMode, s.stereo_preset))
    if device.getPlatform() == dai.Platform.RVC4:
        align = pipeline.create(dai.node.ImageAlign)
        stereo.depth.link(align.input)
        rgb_out.link(align.inputAlignTo)
        depth_out = align.outputAligned
    else:
        rgb_out.link(stereo.inputAlignTo)
        depth_out = stereo.depth
    sync = pipeline.create(dai.node.Sync)
    sync.setSyncThreshold(datetime.timedelta(seconds=0.5 / s.fps))
    rgb_out.link(sync.inputs["rgb"])
    depth_out.link(sync.inputs["depth"])
    rgbd_queue = sync.out.createOutputQueue(maxSize=4, blocking=False)

    imu_queue = None
    if s.imu:
        imu_name = device.getConnectedIMU()
        if imu_name.upper().startswith("BNO"):
            imu = pipeline.create(dai.node.IMU)
            imu.enableIMUSensor(dai.IMUSensor.ROTATION_VECTOR, s.imu_rate_hz)
            imu.setBatchReportThreshold(1)
            imu.setMaxBatchReports(10)
            imu_queue = imu.out.createOutputQueue(maxSize=50, blocking=False)
        else:
            log.warning("OAK IMU %r has no rotation vector (BNO08x only): no OAK attitude",
                        imu_name)

    camera = camera_from_calibration(dai, device.readCalibration(), s)
    pipeline.start()

    def close() -> None:
        try:
            pipeline.stop()
            pipeline.wait()
        finally:
            device.close()

    return OakSession(rgbd_queue, imu_queue, camera, close, name=_device_name(device))


def _device_name(device: Any) -> str:
    try:
        return device.getDeviceId()
    except RuntimeError:
        return "oak"


def camera_from_calibration(dai: ModuleType, calib: Any, s: OakSettings) -> CameraModel:
    """The colour camera at the output size, from the device calibration."""
    k = calib.getCameraIntrinsics(dai.CameraBoardSocket.CAM_A, s.width, s.height)
    distortion: tuple[float, ...] = ()
    if not s.undistort:
        socket = dai.CameraBoardSocket.CAM_A
        coeffs = tuple(float(c) for c in calib.getDistortionCoefficients(socket))
        distortion = coeffs if any(coeffs) else ()
    return CameraModel(
        fx=float(k[0][0]), fy=float(k[1][1]), cx=float(k[0][2]), cy=float(k[1][2]),
        width=s.width, height=s.height, depth_scale=DEPTH_SCALE_MM,
        distortion=distortion, q_B_C_xyzw=s.q_B_C_xyzw,
    )


# --------------------------------------------------------------------------- messages


def timedelta_ns(td: datetime.timedelta) -> int:
    return (td.days * 86400 + td.seconds) * 1_000_000_000 + td.microseconds * 1000


def frame_from_group(dai: ModuleType, group: Any, camera: CameraModel) -> tuple[RgbdFrame, bool]:
    """An RgbdFrame from a Sync MessageGroup; True if the depth image had to
    be resized to the colour size (alignment did not deliver it)."""
    rgb, depth = group["rgb"], group["depth"]
    t_ns = timedelta_ns(rgb.getTimestamp(dai.CameraExposureOffset.MIDDLE))
    bgr = rgb.getCvFrame()
    depth_raw = depth.getFrame()
    resized = depth_raw.shape[:2] != bgr.shape[:2]
    if resized:
        depth_raw = cv2.resize(depth_raw, (bgr.shape[1], bgr.shape[0]),
                               interpolation=cv2.INTER_NEAREST)
    depth_m = depth_raw.astype(np.float32) / np.float32(camera.depth_scale)
    return RgbdFrame(t_s=t_ns * 1e-9, bgr=bgr, depth_m=depth_m), resized


def rotation_vectors(imu_data: Any) -> list[tuple[int, Quat]]:
    """(t_ns, q_xyzw of the IMU in its world) for each packet of an IMUData."""
    out = []
    for packet in imu_data.packets:
        rv = packet.rotationVector
        out.append((timedelta_ns(rv.getTimestamp()), (rv.i, rv.j, rv.k, rv.real)))
    return out


# --------------------------------------------------------------------------- driver


@dataclass(frozen=True)
class OakStats:
    opens: int = 0
    open_failures: int = 0
    disconnects: int = 0  # device lost while running (queue closed, error, frame timeout)
    frame_timeouts: int = 0
    frames: int = 0  # frames handed to the slot
    frames_dropped_in_queue: int = 0  # older groups skipped when several were waiting
    depth_resized: int = 0
    imu_samples: int = 0


class OakDriver(DriverThread):
    """The OAK-D as a camera source (newest-frame slot) and, with `imu_sink`,
    as an attitude source. `dai_loader` and `session_factory` are for tests:
    a stand-in depthai module and a device-less session."""

    def __init__(
        self,
        settings: OakSettings,
        *,
        imu_sink: Callable[[AttitudeSample], object] | None = None,
        dai_loader: Callable[[], ModuleType] = import_depthai,
        session_factory: Callable[[ModuleType, OakSettings], OakSession] = open_oak,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        super().__init__("oak")
        self.device_state = DeviceState("OAK-D", settings.device or "(first found)")
        self.settings = settings
        self.imu_sink = imu_sink
        self.dai_loader = dai_loader
        self.session_factory = session_factory
        self.clock_ns = clock_ns
        self.slot = FrameSlot()
        self.counters: Counters[OakStats] = Counters(OakStats())
        self.backoff = Backoff(settings.reconnect_min_s, settings.reconnect_max_s)
        self._camera: CameraModel | None = None
        self._camera_ready = threading.Event()
        self._imu_world: Quat = _Q_NED_ENU if settings.imu_world == "enu" else IDENTITY_Q_XYZW

    @property
    def stats(self) -> OakStats:
        return self.counters.snapshot()

    # -- CameraSource

    def wait_camera(self, timeout_s: float) -> CameraModel | None:
        self._camera_ready.wait(timeout_s)
        return self._camera

    def take(self, after_seq: int = 0, timeout_s: float = 0.0) -> tuple[int, RgbdFrame] | None:
        return self.slot.take(after_seq, timeout_s)

    @property
    def exhausted(self) -> bool:
        return False

    # -- thread

    def _run(self) -> None:
        try:
            self._run_device()
        finally:
            self.device_state.set(State.CLOSED)

    def _run_device(self) -> None:
        try:
            dai = self.dai_loader()
        except ImportError as e:
            self.device_state.set(State.NO_DEVICE, f"depthai is not installed: {e}")
            return
        first = True
        while not self.stopping:
            settings = self.settings
            if first:
                settings = dataclasses.replace(settings,
                                               search_s=min(settings.search_s, FIRST_SEARCH_S))
                first = False
            try:
                session = self.session_factory(dai, settings)
            except RuntimeError as e:  # depthai reports XLink/boot problems as RuntimeError
                log.info("OAK: cannot open: %s", e)
                self.device_state.set(State.NO_DEVICE, f"cannot open: {e}")
                self.counters.bump(open_failures=1)
                if self._sleep(self.backoff.next()):
                    break
                continue
            self.device_state.set(State.OPEN)
            self.counters.bump(opens=1)
            self._camera = session.camera
            self._camera_ready.set()
            log.info("OAK %s: streaming %dx%d at %g fps%s", session.name, session.camera.width,
                     session.camera.height, self.settings.fps,
                     " with rotation vector" if session.imu_queue is not None else "")
            try:
                self._serve(dai, session)
            except (RuntimeError, dai.MessageQueue.QueueException) as e:
                if not self.stopping:
                    log.info("OAK %s: device lost: %s", session.name, e)
                    if not self.device_state.state.failed:
                        self.device_state.set(State.NO_DEVICE, f"device lost: {e}")
                    self.counters.bump(disconnects=1)
            finally:
                try:
                    session.close()
                except RuntimeError as e:
                    log.debug("OAK: close failed: %s", e)
            if not self.stopping and self._sleep(self.backoff.next()):
                break

    def _serve(self, dai: ModuleType, session: OakSession) -> None:
        queues = [session.rgbd_queue]
        if session.imu_queue is not None:
            queues.append(session.imu_queue)
        poll = datetime.timedelta(seconds=self.settings.poll_s)
        timeout_ns = int(self.settings.frame_timeout_s * 1e9)
        last_frame_ns = self.clock_ns()
        while not self.stopping:
            dai.MessageQueue.waitAny(queues, poll)
            now_ns = self.clock_ns()
            if session.imu_queue is not None:
                for data in session.imu_queue.tryGetAll():
                    self._deliver_imu(data)
            groups = session.rgbd_queue.tryGetAll()
            if groups:
                frame, resized = frame_from_group(dai, groups[-1], session.camera)
                self.slot.put(frame)
                self.counters.bump(frames=1, frames_dropped_in_queue=len(groups) - 1,
                                   depth_resized=int(resized))
                self.device_state.set(State.STREAMING)
                last_frame_ns = now_ns
                self.backoff.reset()
            elif session.rgbd_queue.isClosed():
                self.device_state.set(State.NO_DEVICE, "disconnected (frame queue closed)")
                raise RuntimeError("frame queue closed (device disconnected)")
            elif now_ns - last_frame_ns > timeout_ns:
                self.counters.bump(frame_timeouts=1)
                self.device_state.set(State.SILENT,
                                      f"no frame for {self.settings.frame_timeout_s:g} s")
                raise RuntimeError(f"no frame for {self.settings.frame_timeout_s:g} s")

    def _deliver_imu(self, data: Any) -> None:
        n = 0
        for t_ns, q_xyzw in rotation_vectors(data):
            sample = to_body_sample(t_ns, quat_mul(self._imu_world, q_xyzw),
                                    self.settings.imu_q_B_A_xyzw)
            if sample is not None and self.imu_sink is not None:
                self.imu_sink(sample)
                n += 1
        if n:
            self.counters.bump(imu_samples=n)
