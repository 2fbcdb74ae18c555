"""A stand-in for the `depthai` module: exactly the names drivers/oak.py uses.

`FakeDai(...)` behaves like `import depthai` for the driver: Device search
and open, Pipeline(device), Camera/StereoDepth/ImageAlign/Sync/IMU nodes with
the builder calls the driver makes, output queues, MessageQueue.waitAny,
MessageGroup, ImgFrame, IMUData and CalibrationHandler. A started pipeline
runs a producer thread that emits synchronised colour + depth groups and
rotation-vector packets stamped on the host monotonic clock, as a real
device's host-synced timestamps are.

Faults a test can trigger: `fail_opens` (device searches that find nothing),
`unplug()` (the running device vanishes: its queues close, as depthai does
on USB loss), `stalled = True` (no frames, the device still there), `read_error()` (a queue read raises like depthai's
XLinkReadError, a RuntimeError). `API_NAMES` lists every attribute path the stand-in provides,
so a test can check each exists in the real depthai.
"""

from __future__ import annotations

import datetime
import enum
import math
import threading
import time
from typing import Any

import numpy as np

API_NAMES = (
    "Device", "Device.getAnyAvailableDevice", "Device.getDeviceById", "Device.getPlatform",
    "Device.getConnectedIMU", "Device.readCalibration", "Device.close", "Device.getDeviceId",
    "Pipeline", "Pipeline.create", "Pipeline.start", "Pipeline.stop", "Pipeline.wait",
    "node.Camera", "node.Camera.build", "node.Camera.requestOutput",
    "node.StereoDepth", "node.StereoDepth.build", "node.StereoDepth.depth",
    "node.StereoDepth.inputAlignTo", "node.StereoDepth.PresetMode.DEFAULT",
    "node.ImageAlign", "node.ImageAlign.input", "node.ImageAlign.inputAlignTo",
    "node.ImageAlign.outputAligned",
    "node.Sync", "node.Sync.setSyncThreshold", "node.Sync.inputs", "node.Sync.out",
    "node.IMU", "node.IMU.enableIMUSensor", "node.IMU.setBatchReportThreshold",
    "node.IMU.setMaxBatchReports", "node.IMU.out",
    "Node.Output.link", "Node.Output.createOutputQueue",
    "MessageQueue", "MessageQueue.waitAny", "MessageQueue.tryGetAll", "MessageQueue.isClosed",
    "MessageQueue.QueueException",
    "MessageGroup.__getitem__", "ImgFrame.getTimestamp", "ImgFrame.getCvFrame",
    "ImgFrame.getFrame", "IMUData.packets", "IMUPacket.rotationVector",
    "IMUReportRotationVectorWAcc.i", "IMUReportRotationVectorWAcc.j",
    "IMUReportRotationVectorWAcc.k", "IMUReportRotationVectorWAcc.real",
    "IMUReportRotationVectorWAcc.getTimestamp",
    "CalibrationHandler.getCameraIntrinsics", "CalibrationHandler.getDistortionCoefficients",
    "CameraBoardSocket.CAM_A", "CameraBoardSocket.CAM_B", "CameraBoardSocket.CAM_C",
    "CameraExposureOffset.MIDDLE", "IMUSensor.ROTATION_VECTOR", "Platform.RVC2",
    "Platform.RVC4",
)


class CameraBoardSocket(enum.Enum):
    CAM_A = 0
    CAM_B = 1
    CAM_C = 2


class CameraExposureOffset(enum.Enum):
    START = 0
    MIDDLE = 1
    END = 2


class IMUSensor(enum.Enum):
    ROTATION_VECTOR = 0


class Platform(enum.Enum):
    RVC2 = 0
    RVC4 = 2


def _td(ns: int) -> datetime.timedelta:
    return datetime.timedelta(microseconds=ns // 1000)


class ImgFrame:
    def __init__(self, image: np.ndarray, t_ns: int, exposure_ns: int = 0) -> None:
        self._image = image
        self._t_ns = t_ns
        self._exposure_ns = exposure_ns

    def getTimestamp(self, offset: CameraExposureOffset = CameraExposureOffset.START):
        extra = {CameraExposureOffset.START: 0, CameraExposureOffset.MIDDLE: self._exposure_ns // 2,
                 CameraExposureOffset.END: self._exposure_ns}[offset]
        return _td(self._t_ns + extra)

    def getCvFrame(self) -> np.ndarray:
        return self._image.copy()

    def getFrame(self) -> np.ndarray:
        return self._image


class MessageGroup:
    def __init__(self, messages: dict[str, Any]) -> None:
        self._messages = messages

    def __getitem__(self, name: str) -> Any:
        return self._messages[name]


class IMUReportRotationVectorWAcc:
    def __init__(self, q_xyzw, t_ns: int) -> None:
        self.i, self.j, self.k, self.real = q_xyzw
        self._t_ns = t_ns

    def getTimestamp(self) -> datetime.timedelta:
        return _td(self._t_ns)


class IMUPacket:
    def __init__(self, rv: IMUReportRotationVectorWAcc) -> None:
        self.rotationVector = rv


class IMUData:
    def __init__(self, packets: list[IMUPacket]) -> None:
        self.packets = packets


class MessageQueue:
    class QueueException(Exception):
        pass

    def __init__(self, max_size: int, registry: "_Registry") -> None:
        self._items: list[Any] = []
        self._max = max_size
        self._closed = False
        self._registry = registry

    def _push(self, item: Any) -> None:
        with self._registry.cond:
            self._items.append(item)
            del self._items[: -self._max]  # non-blocking queue: the oldest go
            self._registry.cond.notify_all()

    def _close(self) -> None:
        with self._registry.cond:
            self._closed = True
            self._registry.cond.notify_all()

    def tryGetAll(self) -> list[Any]:
        with self._registry.cond:
            if self._registry.read_error:
                self._registry.read_error = False
                raise RuntimeError("Couldn't read data from stream: 'sync' (X_LINK_ERROR)")
            if self._closed and not self._items:
                raise MessageQueue.QueueException("queue closed")
            items, self._items = self._items, []
            return items

    def isClosed(self) -> bool:
        with self._registry.cond:
            return self._closed

    @staticmethod
    def waitAny(queues: list["MessageQueue"], timeout: datetime.timedelta) -> bool:
        reg = queues[0]._registry
        with reg.cond:
            return reg.cond.wait_for(
                lambda: any(q._items for q in queues) or all(q._closed for q in queues),
                timeout.total_seconds()) and any(q._items for q in queues)


class _Registry:
    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.read_error = False  # the next tryGetAll raises, as an XLinkReadError


class Node:
    class Output:
        def __init__(self, pipeline: "Pipeline", name: str) -> None:
            self.pipeline = pipeline
            self.name = name
            self.targets: list[Any] = []

        def link(self, target: Any) -> None:
            self.targets.append(target)

        def createOutputQueue(self, maxSize: int = 16, blocking: bool = False) -> MessageQueue:
            q = MessageQueue(maxSize, self.pipeline.device.registry)
            self.pipeline.queues[self.name] = q
            return q

    class Input:
        def __init__(self, name: str) -> None:
            self.name = name


class _Camera:
    def __init__(self, pipeline: "Pipeline") -> None:
        self.pipeline = pipeline

    def build(self, socket: CameraBoardSocket) -> "_Camera":
        self.socket = socket
        return self

    def requestOutput(self, size, type=None, resizeMode=None, fps=None,
                      enableUndistortion=None) -> Node.Output:
        out = Node.Output(self.pipeline, f"cam{self.socket.value}")
        out.size, out.fps, out.undistorted = tuple(size), fps, enableUndistortion
        self.pipeline.requested[self.socket] = out
        return out


class _StereoDepth:
    class PresetMode(enum.Enum):
        DEFAULT = 2
        ROBOTICS = 6

    def __init__(self, pipeline: "Pipeline") -> None:
        self.pipeline = pipeline
        self.depth = Node.Output(pipeline, "depth")
        self.inputAlignTo = Node.Input("inputAlignTo")

    def build(self, left: Node.Output, right: Node.Output, presetMode=None) -> "_StereoDepth":
        self.preset = presetMode
        self.pipeline.stereo = self
        return self


class _ImageAlign:
    def __init__(self, pipeline: "Pipeline") -> None:
        self.input = Node.Input("input")
        self.inputAlignTo = Node.Input("inputAlignTo")
        self.outputAligned = Node.Output(pipeline, "aligned")


class _Sync:
    def __init__(self, pipeline: "Pipeline") -> None:
        self.inputs = {"rgb": Node.Input("rgb"), "depth": Node.Input("depth")}
        self.out = Node.Output(pipeline, "sync")
        self.threshold: datetime.timedelta | None = None
        pipeline.sync = self

    def setSyncThreshold(self, threshold: datetime.timedelta) -> None:
        self.threshold = threshold


class _IMU:
    def __init__(self, pipeline: "Pipeline") -> None:
        self.out = Node.Output(pipeline, "imu")
        self.pipeline = pipeline

    def enableIMUSensor(self, sensor: IMUSensor, rate: int) -> None:
        self.pipeline.imu_rate = rate

    def setBatchReportThreshold(self, n: int) -> None:
        pass

    def setMaxBatchReports(self, n: int) -> None:
        pass


class _NodeNamespace:
    Camera = _Camera
    StereoDepth = _StereoDepth
    ImageAlign = _ImageAlign
    Sync = _Sync
    IMU = _IMU


class CalibrationHandler:
    """Intrinsics of a 1920x1080 sensor, scaled like depthai (keepAspectRatio)."""

    K_FULL = ((1500.0, 0.0, 960.0), (0.0, 1500.0, 540.0), (0.0, 0.0, 1.0))

    def getCameraIntrinsics(self, socket, w: int, h: int):
        s = max(w / 1920.0, h / 1080.0)
        (fx, _, cx), (_, fy, cy), _r = self.K_FULL
        crop_x, crop_y = (1920 * s - w) / 2, (1080 * s - h) / 2
        return [[fx * s, 0.0, cx * s - crop_x], [0.0, fy * s, cy * s - crop_y], [0.0, 0.0, 1.0]]

    def getDistortionCoefficients(self, socket) -> list[float]:
        return [0.1, -0.05, 0.0, 0.0, 0.01] + [0.0] * 9


class Device:
    def __init__(self, info: Any) -> None:
        self.dai: FakeDai = info["dai"]
        self.registry = _Registry()
        self.closed = False
        self.pipeline: Pipeline | None = None
        self.dai.devices.append(self)

    @staticmethod
    def getAnyAvailableDevice(timeout: datetime.timedelta):
        raise AssertionError("bound per FakeDai instance")

    def getPlatform(self) -> Platform:
        return self.dai.platform

    def getConnectedIMU(self) -> str:
        return self.dai.imu_name

    def readCalibration(self) -> CalibrationHandler:
        return CalibrationHandler()

    def getDeviceId(self) -> str:
        return "FAKE14442C10D13EABCE00"

    def close(self) -> None:
        self.closed = True
        if self.pipeline is not None:
            self.pipeline.stop()


class Pipeline:
    def __init__(self, device: Device) -> None:
        self.device = device
        device.pipeline = self
        self.queues: dict[str, MessageQueue] = {}
        self.requested: dict[CameraBoardSocket, Node.Output] = {}
        self.stereo: _StereoDepth | None = None
        self.sync: _Sync | None = None
        self.imu_rate = 0
        self.captured_ns: list[int] = []  # frame n's capture stamp (start of exposure)
        self.running = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def create(self, cls: type) -> Any:
        return cls(self)

    def start(self) -> None:
        self.running = True
        self._thread = threading.Thread(target=self._produce, daemon=True, name="fake_oak")
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self.running = False
        for q in self.queues.values():
            q._close()

    def wait(self) -> None:
        if self._thread is not None:
            self._thread.join(5.0)

    def _produce(self) -> None:
        dai = self.device.dai
        rgb = self.requested[CameraBoardSocket.CAM_A]
        w, h = rgb.size
        frame_period = 1.0 / rgb.fps
        imu_period = 1.0 / self.imu_rate if self.imu_rate else None
        next_frame = next_imu = time.monotonic()
        n = 0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_frame and "sync" in self.queues and dai.stalled:
                next_frame += frame_period  # the sensor delivers nothing (stall())
            elif now >= next_frame and "sync" in self.queues:
                t_ns = time.monotonic_ns() - dai.capture_latency_ns
                self.captured_ns.append(t_ns)
                colour = np.full((h, w, 3), n % 256, np.uint8)
                dh, dw = dai.depth_size or (h, w)
                depth = np.full((dh, dw), 1000 + n, np.uint16)
                self.queues["sync"]._push(MessageGroup({
                    "rgb": ImgFrame(colour, t_ns, dai.exposure_ns),
                    "depth": ImgFrame(depth, t_ns)}))
                n += 1
                next_frame += frame_period
            if imu_period and now >= next_imu and "imu" in self.queues:
                t_ns = time.monotonic_ns()
                yaw = dai.imu_yaw_rate * t_ns * 1e-9
                rv = IMUReportRotationVectorWAcc((0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)),
                                                 t_ns)
                self.queues["imu"]._push(IMUData([IMUPacket(rv)]))
                next_imu += imu_period
            due = min(next_frame, next_imu if imu_period else next_frame)
            self._stop.wait(max(0.0, due - time.monotonic()))


class FakeDai:
    """One stand-in depthai 'module'. Attributes mirror depthai's names."""

    CameraBoardSocket = CameraBoardSocket
    CameraExposureOffset = CameraExposureOffset
    IMUSensor = IMUSensor
    Platform = Platform
    MessageQueue = MessageQueue
    Pipeline = Pipeline
    node = _NodeNamespace

    def __init__(self, *, platform: Platform = Platform.RVC2, imu_name: str = "BNO086",
                 fail_opens: int = 0, exposure_ns: int = 8_000_000,
                 capture_latency_ns: int = 30_000_000, imu_yaw_rate: float = 0.5,
                 depth_size: tuple[int, int] | None = None) -> None:
        self.platform = platform
        self.imu_name = imu_name
        self.fail_opens = fail_opens
        self.exposure_ns = exposure_ns
        self.capture_latency_ns = capture_latency_ns
        self.imu_yaw_rate = imu_yaw_rate
        self.depth_size = depth_size
        self.devices: list[Device] = []
        self.searches = 0
        self.stalled = False  # frames stop while the device stays connected
        dai = self

        class _Device(Device):
            @staticmethod
            def getAnyAvailableDevice(timeout: datetime.timedelta):
                dai.searches += 1
                if dai.fail_opens > 0:
                    dai.fail_opens -= 1
                    return False, None
                return True, {"dai": dai}

            @staticmethod
            def getDeviceById(device_id: str):
                dai.searches += 1
                return True, {"dai": dai, "id": device_id}

        self.Device = _Device

    def read_error(self) -> None:
        """The next queue read fails with an XLink error (a RuntimeError)."""
        for dev in self.devices:
            if dev.pipeline is not None and dev.pipeline.running:
                with dev.registry.cond:
                    dev.registry.read_error = True

    def unplug(self) -> None:
        """The running device vanishes: depthai closes its queues."""
        for dev in self.devices:
            if dev.pipeline is not None and dev.pipeline.running:
                dev.pipeline.stop()
