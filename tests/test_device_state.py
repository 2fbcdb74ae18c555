"""Each driver's state, told once: the first failure is one warning line
(device, path, cause), a reminder at most every 30 s, one line on recovery;
`nislam run` with no camera and a missing AHRS port warns for each within 2 s
without -v. The camera is the fake depthai behind the real driver: no device
search happens here."""

from __future__ import annotations

import logging
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent / "peers"))

from fake_depthai import FakeDai  # noqa: E402

from drivers.device_state import DeviceState, State  # noqa: E402
from onboard.app.config import load_config  # noqa: E402
from onboard.app.service import Service  # noqa: E402
from onboard.app.sources import hardware_sources  # noqa: E402


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_first_failure_is_one_line_then_reminders_then_one_recovery_line(caplog):
    clock = Clock()
    ds = DeviceState("myAHRS+", "/dev/ttyUSB9", clock=clock)
    with caplog.at_level(logging.WARNING, logger="drivers.device_state"):
        for _ in range(50):  # every reopen attempt sets the same state again
            ds.set(State.NO_DEVICE, "cannot open: No such file or directory")
            clock.t += 0.5  # 25 s in all: no reminder yet
        clock.t += 5.0
        ds.set(State.NO_DEVICE, "cannot open: No such file or directory")  # 30 s: a reminder
        ds.set(State.OPEN)
        ds.set(State.BAD_DATA, "480 bytes but no valid sample for 1.0 s")  # another failure
        ds.set(State.BAD_DATA, "960 bytes but no valid sample for 2.0 s")
        ds.set(State.STREAMING)
        ds.set(State.STREAMING)
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0] == "myAHRS+ /dev/ttyUSB9: no device: cannot open: No such file or directory"
    assert lines[1].startswith("myAHRS+ /dev/ttyUSB9: still no device after 30 s")
    assert lines[2].startswith("myAHRS+ /dev/ttyUSB9: bad data: 480 bytes")
    assert lines[3].startswith("myAHRS+ /dev/ttyUSB9: recovered, streaming again")
    assert len(lines) == 4
    snap = ds.snapshot()
    assert snap.state is State.STREAMING and snap.failures == 1
    assert snap.text() == "myAHRS+ streaming"


def test_run_without_camera_and_ahrs_warns_for_each_within_2_s(tmp_path, caplog):
    dai = FakeDai(fail_opens=10**6)  # no OAK-D connected
    cfg = load_config(None, {"ahrs.source": "myahrs", "myahrs.port": str(tmp_path / "ttyAHRS"),
                             "service.stats_period_s": 0.5})
    sources = hardware_sources(cfg, dai_loader=lambda: dai)
    lines: list[str] = []
    svc = Service(cfg, sources, threading.Event(), seconds=2.5, emit=lines.append)
    t0 = time.monotonic()
    t_wall0 = time.time()  # what record.created counts on
    with caplog.at_level(logging.WARNING):
        svc.run()
    warned = {}
    for r in caplog.records:
        if r.levelno >= logging.WARNING and r.name == "drivers.device_state":
            warned.setdefault(r.getMessage().split(":")[0], (r.created, r.getMessage()))
    assert set(warned) == {"OAK-D (first found)", f"myAHRS+ {tmp_path / 'ttyAHRS'}"}, warned
    assert all(created - t_wall0 < 2.0 for created, _m in warned.values()), warned
    assert "No such file or directory" in warned[f"myAHRS+ {tmp_path / 'ttyAHRS'}"][1]
    assert "no OAK device" in warned["OAK-D (first found)"][1]
    # One line each, not one per retry; the health line carries both states.
    assert sum(r.name == "drivers.device_state" for r in caplog.records) == 2
    assert lines and "OAK-D no device" in lines[-1] and "myAHRS+ no device" in lines[-1]
    assert "OAK-D no device" in svc.health.report.reason
    assert time.monotonic() - t0 < 10


class _Undeclarable:
    def undeclare(self) -> None:
        pass


class RecordingSession:
    """The part of a zenoh.Session that ZenohOutput uses; puts recorded."""

    def __init__(self) -> None:
        self.puts: list[tuple[str, bytes]] = []
        self.cond = threading.Condition()

    def put(self, key: str, payload, **kwargs) -> None:
        with self.cond:
            self.puts.append((key, payload))
            self.cond.notify_all()

    def declare_publisher(self, key: str, **kwargs):
        session = self

        class Publisher(_Undeclarable):
            def put(self, payload) -> None:
                session.put(key, payload)

            def declare_matching_listener(self, callback) -> _Undeclarable:
                return _Undeclarable()

        return Publisher()

    def declare_queryable(self, key: str, callback) -> _Undeclarable:
        return _Undeclarable()

    def liveliness(self):
        return self

    def declare_token(self, key: str) -> _Undeclarable:
        return _Undeclarable()


def test_the_zenoh_status_carries_each_driver_state():
    import json

    from onboard.core.messages import Health, HealthReport
    from onboard.outputs.settings import ZenohConfig
    from onboard.outputs.zenoh_out import ZenohOutput

    session = RecordingSession()
    out = ZenohOutput(ZenohConfig(vehicle="v9", status_period_s=0.05), session=session)
    devices = ("OAK-D no device (cannot open: no OAK device available)", "myAHRS+ streaming")
    try:
        out.publish_health(HealthReport(Health.LOST, "no frames for 2.0 s", True, devices))

        def carried() -> bool:
            return any(k.endswith("/status") and json.loads(p).get("devices") == list(devices)
                       for k, p in session.puts)

        with session.cond:
            assert session.cond.wait_for(carried, 30.0), session.puts[-3:]
    finally:
        out.close(10.0)
