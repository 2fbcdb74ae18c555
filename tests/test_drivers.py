"""Driver building blocks: the attitude buffer, the newest-frame slot, driver
threads, quaternion conventions, the driver config sections and import hygiene."""

from __future__ import annotations

import math
import subprocess
import sys
import threading

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from onboard import NislamError
from onboard.app.config import Config, load_config
from onboard.core.attitude import AttitudeBuffer, AttitudeSample, to_body_sample
from onboard.core.messages import RgbdFrame
from onboard.core.rotations import MOUNT_R_B_C, R_NED_ENU, matrix_to_quat, mount_rotation, quat_mul
from onboard.core.sources import Backoff, Counters, DriverThread, FrameSlot


def yaw_q(rad: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(rad / 2), math.cos(rad / 2))


def angle_deg(r_a: np.ndarray, r_b: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(r_a.T @ r_b).magnitude()))


def filled_buffer(**kwargs) -> AttitudeBuffer:
    buf = AttitudeBuffer(**kwargs)
    for i in range(11):  # 100 Hz, yaw 0 .. 10 deg over 0.1 s
        assert buf.push(AttitudeSample(1_000_000_000 + i * 10_000_000, yaw_q(math.radians(i))))
    return buf


# --------------------------------------------------------------------------- attitude buffer


def test_buffer_interpolates_between_samples() -> None:
    buf = filled_buffer()
    r = buf.body_rotation_at(1.035)
    expected = Rotation.from_euler("z", 3.5, degrees=True).as_matrix()
    assert angle_deg(r, expected) < 1e-6
    assert angle_deg(buf.rotation_at(1.0), np.eye(3)) < 1e-9  # exact on a sample
    # The default mount is identity: R_W_C = R_W_B.
    assert np.allclose(buf.rotation_at(1.035), r)


def test_buffer_applies_the_camera_mount() -> None:
    buf = filled_buffer(R_B_C=MOUNT_R_B_C["forward"])
    r_w_c = buf.rotation_at(1.05)
    assert np.allclose(r_w_c, buf.body_rotation_at(1.05) @ MOUNT_R_B_C["forward"])
    # Forward mount: the optical axis (camera z) is the body's nose (x).
    assert np.allclose(MOUNT_R_B_C["forward"] @ [0, 0, 1], [1, 0, 0])
    assert np.allclose(MOUNT_R_B_C["down"] @ [0, 0, 1], [0, 0, 1])
    assert np.allclose(MOUNT_R_B_C["down"] @ [0, -1, 0], [1, 0, 0])  # image top to the nose
    for r in MOUNT_R_B_C.values():
        assert np.allclose(r @ r.T, np.eye(3)) and np.isclose(np.linalg.det(r), 1.0)


def test_buffer_says_no_attitude_outside_its_span() -> None:
    buf = filled_buffer()
    assert buf.rotation_at(0.999) is None  # before the oldest sample
    assert buf.rotation_at(1.101) is None  # after the newest: no extrapolation
    assert buf.rotation_at(float("nan")) is None


def test_buffer_answers_a_late_query_from_the_samples_around_it() -> None:
    """A frame captured while the AHRS talked keeps its attitude however late
    it is asked for (the loop stalled); one captured after the AHRS went
    silent has none, until the AHRS passes its capture time."""
    buf = filled_buffer()
    r = buf.rotation_at(1.05)  # asked for at any later time: no clock involved
    assert r is not None and angle_deg(r, Rotation.from_euler("z", 5, degrees=True).as_matrix()) < 1e-6
    assert buf.rotation_at(1.15) is None  # captured during the silence
    buf.push(AttitudeSample(1_160_000_000, yaw_q(0.0)))  # the sensor is back
    assert buf.rotation_at(1.15) is not None


def test_buffer_wait_covered_wakes_on_the_covering_sample() -> None:
    buf = filled_buffer()
    assert buf.wait_covered(1.1, 0.0) and not buf.wait_covered(1.2, 0.0)
    th = threading.Thread(target=lambda: buf.push(AttitudeSample(1_200_000_000, yaw_q(0.0))))
    th.start()
    assert buf.wait_covered(1.2, 30.0)
    th.join(30)


def test_buffer_does_not_bridge_gaps() -> None:
    buf = AttitudeBuffer(max_gap_s=0.1)
    buf.push(AttitudeSample(1_000_000_000, yaw_q(0.0)))
    buf.push(AttitudeSample(1_300_000_000, yaw_q(0.1)))  # a 0.3 s outage
    assert buf.rotation_at(1.15) is None
    assert buf.rotation_at(1.3) is not None  # a sample stands for itself


def test_buffer_rejects_out_of_order_and_invalid_samples() -> None:
    buf = filled_buffer()
    assert not buf.push(AttitudeSample(1_050_000_000, yaw_q(0.0)))  # older than the newest
    assert not buf.push(AttitudeSample(1_100_000_000, yaw_q(0.0)))  # same stamp
    assert not buf.push(AttitudeSample(1_200_000_000, (0.0, 0.0, 0.0, 0.0)))
    assert not buf.push(AttitudeSample(1_200_000_000, (math.nan, 0.0, 0.0, 1.0)))
    s = buf.stats
    assert (s.pushed, s.rejected_out_of_order, s.rejected_invalid) == (11, 2, 2)
    # Quaternions are normalised on the way in.
    assert buf.push(AttitudeSample(1_110_000_000, (0.0, 0.0, 0.0, 2.0)))
    assert buf.newest().q_W_B_xyzw == (0.0, 0.0, 0.0, 1.0)


def test_buffer_is_bounded() -> None:
    buf = AttitudeBuffer(capacity=8)
    for i in range(100):
        buf.push(AttitudeSample(i * 10_000_000, yaw_q(0.0)))
    assert len(buf) == 8
    assert len(buf._samples) < 16  # trimmed in chunks
    assert buf.rotation_at(0.91) is None  # forgotten
    assert buf.rotation_at(0.95) is not None
    assert [s.t_ns for s in buf.samples_after(None)] == [i * 10_000_000 for i in range(92, 100)]
    assert [s.t_ns for s in buf.samples_after(970_000_000)] == [980_000_000, 990_000_000]


def test_buffer_slerp_takes_the_short_way() -> None:
    buf = AttitudeBuffer()
    q0 = yaw_q(math.radians(170))
    q1 = tuple(-c for c in yaw_q(math.radians(-170)))  # the same rotation as +190 deg, sign flipped
    buf.push(AttitudeSample(0, q0))
    buf.push(AttitudeSample(10_000_000, q1))
    r = buf.body_rotation_at(0.005)
    assert angle_deg(r, Rotation.from_euler("z", 180, degrees=True).as_matrix()) < 1e-6


def test_buffer_is_safe_across_threads() -> None:
    buf = AttitudeBuffer(capacity=64)
    stop = threading.Event()
    errors: list[BaseException] = []

    def writer() -> None:
        t = 0
        while not stop.is_set():
            t += 1_000_000
            buf.push(AttitudeSample(10**12 - 10**9 + t, yaw_q(t * 1e-9)))

    th = threading.Thread(target=writer)
    th.start()
    try:
        for _ in range(2000):
            newest = buf.newest()
            if newest is None:
                continue
            try:
                r = buf.rotation_at(newest.t_s - 0.01)
                assert r is None or np.allclose(r @ r.T, np.eye(3), atol=1e-9)
            except BaseException as e:  # noqa: BLE001 - collected and re-raised below
                errors.append(e)
    finally:
        stop.set()
        th.join(60)
    assert not errors and not th.is_alive()


# --------------------------------------------------------------------------- conventions


def test_body_sample_uses_the_ahrs_to_body_rotation() -> None:
    # An AHRS mounted yawed +90 deg in the body: R_B_A = Rz(90). When the AHRS
    # reports R_W_A = Rz(90), the body itself is level and north: R_W_B = I.
    q_b_a = yaw_q(math.pi / 2)
    s = to_body_sample(5, yaw_q(math.pi / 2), q_b_a)
    assert s is not None and s.t_ns == 5
    r = Rotation.from_quat(s.q_W_B_xyzw).as_matrix()
    assert angle_deg(r, np.eye(3)) < 1e-9
    assert to_body_sample(5, (0.0, 0.0, 0.0, 0.0), q_b_a) is None


def test_quaternion_helpers_match_scipy() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        a, b = Rotation.random(random_state=rng), Rotation.random(random_state=rng)
        q = quat_mul(tuple(a.as_quat()), tuple(b.as_quat()))
        assert angle_deg(Rotation.from_quat(q).as_matrix(), (a * b).as_matrix()) < 1e-9
    r = Rotation.random(random_state=rng).as_matrix()
    assert angle_deg(Rotation.from_quat(matrix_to_quat(r)).as_matrix(), r) < 1e-9
    # ENU -> NED is a proper rotation swapping x/y and flipping z.
    assert np.isclose(np.linalg.det(R_NED_ENU), 1.0)
    assert np.allclose(R_NED_ENU @ [1, 0, 0], [0, 1, 0])  # east is NED y


def test_mount_rotation_presets_and_custom() -> None:
    assert np.allclose(mount_rotation("forward"), MOUNT_R_B_C["forward"])
    q = tuple(Rotation.from_euler("y", 30, degrees=True).as_quat())
    assert np.allclose(mount_rotation("custom", q), Rotation.from_quat(q).as_matrix())
    with pytest.raises(NislamError):
        mount_rotation("sideways")


# --------------------------------------------------------------------------- frame slot


def frame(t_s: float) -> RgbdFrame:
    return RgbdFrame(t_s, np.zeros((2, 2, 3), np.uint8), np.zeros((2, 2), np.float32))


def test_slot_hands_over_the_newest_and_drops_stale_frames() -> None:
    slot = FrameSlot()
    assert slot.take(0, 0.0) is None
    slot.put(frame(1.0))
    slot.put(frame(2.0))  # frame 1 was never taken: dropped
    seq, f = slot.take(0, 0.0)
    assert (seq, f.t_s) == (2, 2.0)
    assert slot.take(seq, 0.0) is None  # nothing newer
    slot.put(frame(3.0))
    assert slot.take(seq, 0.0)[1].t_s == 3.0
    assert slot.stats.put == 3 and slot.stats.taken == 2 and slot.stats.dropped == 1


def test_slot_take_waits_for_a_frame_and_wakes_on_close() -> None:
    slot = FrameSlot()
    got: list = []
    th = threading.Thread(target=lambda: got.append(slot.take(0, 30.0)))
    th.start()
    slot.put(frame(1.0))
    th.join(30)
    assert got and got[0][1].t_s == 1.0
    th = threading.Thread(target=lambda: got.append(slot.take(1, 30.0)))
    th.start()
    slot.close()
    th.join(30)
    assert not th.is_alive() and got[1] is None and slot.closed


def test_slot_wait_taken_returns_once_the_frame_or_a_newer_one_was_taken() -> None:
    slot = FrameSlot()
    seq = slot.put(frame(1.0))
    assert slot.wait_taken(seq, 0.0) is False  # not taken yet
    waited: list[bool] = []
    th = threading.Thread(target=lambda: waited.append(slot.wait_taken(seq, 30.0)))
    th.start()
    slot.put(frame(2.0))  # frame 1 dropped: taking frame 2 takes it past seq
    assert slot.take(0, 0.0)[0] == 2
    th.join(30)
    assert waited == [True]
    seq = slot.put(frame(3.0))
    th = threading.Thread(target=lambda: waited.append(slot.wait_taken(seq, 30.0)))
    th.start()
    slot.close()  # a closed slot releases the source too
    th.join(30)
    assert waited == [True, True] and not th.is_alive()


# --------------------------------------------------------------------------- threads


class Sleeper(DriverThread):
    def __init__(self) -> None:
        super().__init__("sleeper")
        self.started = threading.Event()

    def _run(self) -> None:
        self.started.set()
        while not self._sleep(3600.0):  # a long wait that stop() must cut short
            pass


def test_driver_thread_stops_on_its_event() -> None:
    with Sleeper() as s:  # leaving stops it, joining for at most 5 s
        assert s.started.wait(60)
        assert s.alive
    assert not s.alive and s.last_stop_s is not None  # it did not sleep the hour out
    print(f"stop time {s.last_stop_s * 1e3:.2f} ms")


def test_backoff_doubles_up_to_its_ceiling() -> None:
    b = Backoff(0.1, 0.5)
    assert [b.next() for _ in range(5)] == [0.1, 0.2, 0.4, 0.5, 0.5]
    b.reset()
    assert b.next() == 0.1


def test_counters_wake_waiters() -> None:
    from dataclasses import dataclass

    @dataclass(frozen=True)
    class C:
        n: int = 0

    c = Counters(C())
    th = threading.Thread(target=lambda: [c.bump(n=1) for _ in range(5)])
    th.start()
    assert c.wait_for(lambda s: s.n == 5, 60)
    th.join(60)


# --------------------------------------------------------------------------- config and imports


def test_driver_config_sections_load_and_validate(tmp_path) -> None:
    cfg = load_config(None)
    assert cfg.ahrs.source == "myahrs" and cfg.myahrs.baud == 115200
    assert cfg.autopilot.rate_hz == 50.0 and cfg.oak.fps == 30.0 and cfg.record.png_compression == 1
    path = tmp_path / "x.toml"
    for text, key in [
        ('[ahrs]\nsource = "imu"\n', "ahrs.source"),
        ("[myahrs]\ndivider = 0\n", "myahrs.divider"),
        ("[myahrs]\nq_B_A_xyzw = [0.0, 0.0, 0.0, 2.0]\n", "myahrs.q_B_A_xyzw"),
        ("[autopilot]\nrate_hz = 0\n", "autopilot.rate_hz"),
        ('[oak]\nstereo_preset = "FAST"\n', "oak.stereo_preset"),
        ("[record]\npng_compression = 10\n", "record.png_compression"),
    ]:
        path.write_text(text)
        with pytest.raises(NislamError, match=key.replace(".", r"\.")):
            load_config(path)
    assert Config().ahrs.max_age_s > 0


def test_importing_drivers_has_no_side_effects() -> None:
    """No depthai, no pymavlink, no MAVLINK20 until a driver needs them."""
    code = (
        "import os, sys\n"
        "import onboard.core.attitude, onboard.core.sources, drivers.myahrs, drivers.fc_link\n"
        "import drivers.autopilot_attitude, drivers.oak, onboard.app.hardware, onboard.app.record\n"
        "import sim_replay.sources\n"
        "assert 'depthai' not in sys.modules, 'depthai imported'\n"
        "assert 'pymavlink' not in sys.modules, 'pymavlink imported'\n"
        "assert 'MAVLINK20' not in os.environ\n"
        "from drivers.fc_link import import_mavutil\n"
        "m = import_mavutil()\n"
        "assert os.environ['MAVLINK20'] == '1' and m.mavlink.WIRE_PROTOCOL_VERSION == '2.0'\n"
        "assert hasattr(m.mavlink, 'MAVLink_odometry_message')\n"
    )
    env = {k: v for k, v in __import__("os").environ.items() if k != "MAVLINK20"}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, env=env)
    assert proc.returncode == 0, proc.stderr


def test_import_mavutil_repairs_a_v1_import() -> None:
    """pymavlink imported first without MAVLINK20 (v1 dialect): the lazy
    import switches it to MAVLink 2."""
    code = (
        "from pymavlink import mavutil\n"
        "assert mavutil.mavlink.WIRE_PROTOCOL_VERSION == '1.0'\n"
        "from drivers.fc_link import import_mavutil\n"
        "assert import_mavutil().mavlink.WIRE_PROTOCOL_VERSION == '2.0'\n"
    )
    env = {k: v for k, v in __import__("os").environ.items() if k != "MAVLINK20"}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, env=env)
    assert proc.returncode == 0, proc.stderr
