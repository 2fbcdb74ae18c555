"""The MAVLink feed's pure part: frames, quaternion, velocity, covariance,
reset counter and state, from literal tracker results (no sockets)."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fake_results import POSE_VAR, track_result
from scipy.spatial.transform import Rotation

from onboard import NislamError
from onboard.core.messages import TrackState
from onboard.core.rotations import MOUNT_R_B_C, mount_rotation
from onboard.outputs.mavlink_feed import FeedState, VisionFeed, diag_cov21, euler_rpy, q_wxyz
from onboard.outputs.mavlink_origin import OriginHandshake, ResetCounterStore, state_directory
from onboard.outputs.settings import MavlinkConfig

DT = 1.0 / 30.0
S = math.sqrt(0.5)
R_B_C_FORWARD, R_B_C_DOWN = MOUNT_R_B_C["forward"], MOUNT_R_B_C["down"]


def rz(deg: float) -> np.ndarray:
    return Rotation.from_euler("z", deg, degrees=True).as_matrix()


def test_mount_presets_follow_the_design_conventions() -> None:
    ex, ey, ez = np.eye(3)
    # forward: camera z = body x, camera x = body y, camera y = body z
    assert np.array_equal(R_B_C_FORWARD @ ez, ex)
    assert np.array_equal(R_B_C_FORWARD @ ex, ey)
    assert np.array_equal(R_B_C_FORWARD @ ey, ez)
    # down: camera z = body z (down), image top (-camera y) towards the nose
    assert np.array_equal(R_B_C_DOWN @ ez, ez)
    assert np.array_equal(R_B_C_DOWN @ -ey, ex)
    for r in (R_B_C_FORWARD, R_B_C_DOWN):
        assert np.isclose(np.linalg.det(r), 1.0)
    assert np.allclose(mount_rotation("custom", (0.5, 0.5, 0.5, 0.5)),
                       Rotation.from_quat([0.5, 0.5, 0.5, 0.5]).as_matrix())
    assert np.array_equal(mount_rotation("custom"), np.eye(3))
    with pytest.raises(NislamError):
        mount_rotation("custom", (0.0, 0.0, 0.0, 0.0))
    with pytest.raises(NislamError):
        mount_rotation("sideways")


def test_quaternion_is_w_first_for_a_known_pose() -> None:
    """Body yawed 90 deg (nose east in a NED-like world): q = (cos 45, 0, 0, sin 45)."""
    assert np.allclose(q_wxyz(rz(90)), [S, 0.0, 0.0, S])
    assert np.allclose(q_wxyz(np.eye(3)), [1.0, 0.0, 0.0, 0.0])
    assert q_wxyz(rz(-179))[0] >= 0.0  # sign fixed: w >= 0
    r = Rotation.from_euler("ZYX", [30.0, 10.0, 5.0], degrees=True).as_matrix()
    assert np.allclose(np.degrees(euler_rpy(r)), [5.0, 10.0, 30.0])


def test_pose_in_local_frd_with_the_mount_applied() -> None:
    feed = VisionFeed(R_B_C_FORWARD, "frd")
    R_W_B = rz(90)
    ev = feed.update(track_result(10.0, [1.0, 2.0, 3.0], R_W_B @ R_B_C_FORWARD))
    s = ev.sample
    assert s is not None
    assert s.time_usec == 10_000_000
    assert np.allclose(s.p_L_m, [1.0, 2.0, 3.0])  # the sensor's position, no lever arm
    assert np.allclose(s.q_wxyz, [S, 0.0, 0.0, S])  # the body's orientation
    assert np.allclose(s.pose_var, POSE_VAR)

    flu = VisionFeed(np.eye(3), "flu")  # z-up world, camera = body
    s = flu.update(track_result(10.0, [1.0, 2.0, 3.0], np.eye(3))).sample
    assert np.allclose(s.p_L_m, [1.0, -2.0, -3.0])
    assert np.allclose(s.q_wxyz, [0.0, 1.0, 0.0, 0.0])  # half turn about x


def test_body_velocity_and_rates_from_successive_poses() -> None:
    feed = VisionFeed(R_B_C_FORWARD, velocity_window_s=0.1)
    R_W_C = rz(90) @ R_B_C_FORWARD  # nose east
    samples = []
    for i in range(10):
        ev = feed.update(track_result(5.0 + i * DT, [0.03 * i, 0.0, 0.0], R_W_C))
        samples.append(ev.sample)
    assert np.isnan(samples[0].v_B_m_s).all()  # unknown on the first pose
    assert np.isnan(diag_cov21(samples[0].twist_var_B)[0])
    for s in samples[1:]:
        # 0.9 m/s north while facing east: to the body's left (-y)
        assert np.allclose(s.v_B_m_s, [0.0, -0.9, 0.0], atol=1e-9)
        assert np.allclose(s.v_L_m_s, [0.9, 0.0, 0.0], atol=1e-9)
        assert np.allclose(s.w_B_rad_s, 0.0, atol=1e-12)
    # the window: up to 0.1 s back -> 3 frames at 30 Hz; variances / dt^2
    dt = 3 * DT
    assert np.allclose(samples[-1].v_var_L, (POSE_VAR[:3] + POSE_VAR[:3]) / dt**2)
    # body x is world y for this heading
    assert np.isclose(samples[-1].twist_var_B[0], 2 * POSE_VAR[1] / dt**2)

    yawing = VisionFeed(np.eye(3), velocity_window_s=0.0)
    yawing.update(track_result(0.0, [0, 0, 0], rz(0)))
    s = yawing.update(track_result(0.1, [0, 0, 0], rz(1))).sample
    assert np.allclose(s.w_B_rad_s, [0.0, 0.0, math.radians(1) / 0.1])


def test_covariance_diagonal_indices() -> None:
    cov = diag_cov21(np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]))
    assert [i for i, v in enumerate(cov) if v] == [0, 6, 11, 15, 18, 20]
    assert [cov[i] for i in (0, 6, 11, 15, 18, 20)] == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    unknown = diag_cov21(np.array([np.nan, 1, 1, 1, 1, 1]))
    assert math.isnan(unknown[0]) and not any(unknown[1:])


def run(feed: VisionFeed, spec: list[tuple]) -> list:
    """spec rows: (trusted, tracker reset_counter, x, quality)."""
    events = []
    for i, (trusted, rc, x, quality) in enumerate(spec):
        r = track_result(100.0 + i * DT, [x, 0.0, 0.0], trusted=trusted, reset_counter=rc,
                         quality=quality, lost_reason="peak too weak",
                         state=None if trusted or i > 1 else TrackState.INITIALIZING)
        events.append(feed.update(r))
    return events


def scenario() -> list[tuple]:
    rows = [(False, 0, 0.0, 0)] * 2  # initialising
    rows += [(True, 0, 0.01 * i, 60) for i in range(8)]  # 2-9 tracking
    rows += [(False, 0, 0.0, 0)] * 2  # 10-11 lost
    rows += [(True, 1, 0.5 + 0.01 * i, 60) for i in range(8)]  # 12-19 restart (tracker reset)
    rows += [(True, 1, 2.0 + 0.01 * i, 60) for i in range(10)]  # 20 jumps 1.43 m, then on
    rows += [(True, 2, 2.1 + 0.01 * i, 60) for i in range(5)]  # 30 relocalised while tracking
    rows += [(True, 2, 2.2, 10)] * 3  # 35-37 low quality: degraded
    rows += [(True, 2, 2.2, 22)] * 2  # 38-39 within the hysteresis: still degraded
    rows += [(True, 2, 2.2, 40)] * 2  # 40-41 back to active
    return rows


def test_reset_counter_and_states_follow_the_tracker() -> None:
    feed = VisionFeed(np.eye(3), degraded_quality=20)
    events = run(feed, scenario())
    sent = [(i, e.sample.reset_counter) for i, e in enumerate(events) if e.sample is not None]
    trusted = [i for i, row in enumerate(scenario()) if row[0]]
    assert [i for i, _ in sent] == trusted  # a pose for every trusted frame, no other
    counters = dict(sent)
    assert {counters[i] for i in range(2, 10)} == {0}
    assert {counters[i] for i in range(12, 20)} == {1}  # lost + tracker reset: one bump
    assert {counters[i] for i in range(20, 30)} == {2}  # jump
    assert {counters[i] for i in range(30, 42)} == {3}  # tracker reset while tracking
    assert feed.resets == 3
    changes = [(i, e.state) for i, e in enumerate(events) if e.changed]
    assert changes == [
        (0, FeedState.STANDBY), (2, FeedState.ACTIVE), (10, FeedState.LOST),
        (12, FeedState.ACTIVE), (35, FeedState.DEGRADED), (40, FeedState.ACTIVE),
    ]
    texts = [t for e in events for _sev, t in e.notices + e.texts]
    assert texts == [
        "initialising", "tracking, quality 60", "lost: peak too weak", "reset 1: lost",
        "tracking, quality 60", "reset 2: jump 1.43 m", "reset 3: tracker reset",
        "degraded, quality 10", "tracking, quality 40",
    ]
    assert feed.quality == 40


def test_a_loop_closure_is_announced_as_a_reset() -> None:
    """A loop correction steps the pose by the drift it removed (here 4 cm,
    under jump_m, so the jump rule alone would let the autopilot fuse it as
    motion): the first pose after loop_corrections went up carries
    reset_counter + 1, once, with a STATUSTEXT saying why."""
    feed = VisionFeed(np.eye(3), jump_m=0.1)
    xs = [0.01 * i for i in range(5)] + [0.04 + 0.04 + 0.01 * i for i in range(5)]
    loops = [0] * 5 + [1] * 5
    events = [feed.update(dataclasses.replace(track_result(i * DT, [x, 0.0, 0.0]),
                                              loop_corrections=n))
              for i, (x, n) in enumerate(zip(xs, loops))]
    assert [e.sample.reset_counter for e in events] == [0] * 5 + [1] * 5
    assert feed.resets == 1
    assert [t for e in events for _sev, t in e.notices] == ["reset 1: loop closure"]


def test_slow_moves_are_not_jumps_and_the_counter_wraps() -> None:
    feed = VisionFeed(np.eye(3), jump_m=0.1, jump_speed_m_s=10.0)
    feed.update(track_result(0.0, [0, 0, 0]))
    assert feed.update(track_result(1.0, [5.0, 0, 0])).sample.reset_counter == 0  # 5 m/s
    assert feed.update(track_result(1.0 + DT, [5.05, 0, 0])).sample.reset_counter == 0
    feed.reset_counter = 255
    assert feed.update(track_result(1.0 + 2 * DT, [7.0, 0, 0])).sample.reset_counter == 0


def test_stale_feed_is_lost_once_and_resumes_with_a_bump() -> None:
    feed = VisionFeed(np.eye(3))
    assert feed.stale(1.0) is None  # nothing started yet
    feed.update(track_result(0.0, [0, 0, 0]))
    ev = feed.stale(0.6)
    assert ev is not None and ev.state is FeedState.LOST and ev.changed
    assert ev.texts[0][1] == "lost: no frames for 0.6 s"
    assert feed.stale(1.6) is None  # once
    assert feed.quality == -1
    ev = feed.update(track_result(2.0, [0, 0, 0]))
    assert ev.sample.reset_counter == 1 and ev.state is FeedState.ACTIVE


def test_importing_the_outputs_has_no_side_effects() -> None:
    """pymavlink, zenoh and MAVLINK20 stay untouched until an output is built."""
    code = (
        "import os, sys\n"
        "import onboard.outputs.group, onboard.outputs.mavlink, onboard.outputs.mapcodec, onboard.app.cli\n"
        "assert 'pymavlink' not in sys.modules, 'pymavlink imported'\n"
        "assert 'zenoh' not in sys.modules, 'zenoh imported'\n"
        "assert 'MAVLINK20' not in os.environ\n"
        "from onboard.outputs.mavlink import load_mavutil\n"
        "m = load_mavutil()\n"
        "assert os.environ['MAVLINK20'] == '1' and m.mavlink.WIRE_PROTOCOL_VERSION == '2.0'\n"
        "assert hasattr(m.mavlink.MAVLink, 'odometry_send')\n"
    )
    env = {k: v for k, v in __import__("os").environ.items() if k != "MAVLINK20"}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr

    refused = subprocess.run(
        [sys.executable, "-c", "from pymavlink import mavutil\n"
         "from onboard.outputs.mavlink import load_mavutil\nload_mavutil()"],
        env=env, capture_output=True, text=True, timeout=120)
    assert refused.returncode != 0 and "MAVLink 1" in refused.stderr


# --------------------------------------------------------------------------- restarts


def test_a_new_process_starts_one_above_the_last_counter_sent(tmp_path) -> None:
    store = ResetCounterStore(tmp_path / "state")
    first = store.start_counter(clock_s=1234.5)  # nothing kept yet: from the clock
    assert first == 12345 % 256
    feed = VisionFeed(np.eye(3), start_counter=first)
    assert feed.update(track_result(0.0, [0, 0, 0])).sample.reset_counter == first
    store.save(first)
    ev = feed.update(track_result(DT, [5.0, 0, 0]))  # a jump
    store.save(ev.sample.reset_counter)
    # The next process (the same directory) announces its new origin with +1.
    nxt = ResetCounterStore(tmp_path / "state").start_counter(clock_s=1234.5)
    assert nxt == (first + 2) % 256 != ev.sample.reset_counter
    (tmp_path / "state" / "mavlink_reset_counter").write_text("255\n")
    assert ResetCounterStore(tmp_path / "state").start_counter() == 0  # uint8 wraps


def test_the_counter_store_never_raises(tmp_path, caplog) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    store = ResetCounterStore(blocker / "state")
    store.save(3)
    store.save(4)
    assert store.saved is None
    assert sum("cannot keep reset_counter" in r.message for r in caplog.records) == 1  # once
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "mavlink_reset_counter").write_text("garbage")
    assert ResetCounterStore(tmp_path / "bad").start_counter(clock_s=2.0) == 20


def test_state_directory_follows_systemd_then_xdg() -> None:
    assert state_directory("/srv/x", {"STATE_DIRECTORY": "/var/lib/nislam"}) == Path("/srv/x")
    assert state_directory("", {"STATE_DIRECTORY": "/var/lib/nislam:/var/lib/other"}) == Path(
        "/var/lib/nislam")
    assert state_directory("", {"XDG_STATE_HOME": "/h/.st"}) == Path("/h/.st/nislam")
    assert state_directory("", {"HOME": "/home/u"}) == Path("/home/u/.local/state/nislam")


def test_time_usec_is_the_host_time_of_a_replayed_stamp() -> None:
    feed = VisionFeed(np.eye(3), host_time_s=lambda t: 5000.0 + (t - 1000.0) / 0.5)
    ev = feed.update(track_result(1001.0, [0, 0, 0]))
    assert ev.sample.time_usec == 5002_000_000
    ev = feed.update(track_result(1001.0 + DT, [0.01, 0, 0]))
    # ... while velocities stay those of the recording's own time base
    assert ev.sample.v_L_m_s[0] == pytest.approx(0.01 / DT)


def test_origin_home_only_when_asked() -> None:
    cfg = MavlinkConfig(set_origin=True, origin_lat_deg=1.0, origin_lon_deg=2.0)
    assert [m for m, _ in OriginHandshake(cfg).messages(0.0, 0)] == ["set_gps_global_origin"]
    cfg = dataclasses.replace(cfg, set_home=True)
    assert [m for m, _ in OriginHandshake(cfg).messages(0.0, 0)] == [
        "set_gps_global_origin", "set_home_position"]
