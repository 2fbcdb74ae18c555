"""The MAVLink feed received by a pymavlink peer in another process on
127.0.0.1 (tests/mavlink_peer.py), field by field."""

from __future__ import annotations

import logging
import math
import socket
import threading
import time

import numpy as np
import pytest
from fake_results import POSE_VAR, track_result
from scipy.spatial.transform import Rotation
from subproc import REPO, JsonLinesProcess, free_port, python_script

from onboard.core.messages import TrackState
from onboard.core.rotations import MOUNT_R_B_C
from onboard.outputs.mavlink import MavlinkOutput
from onboard.outputs.settings import MavlinkConfig

PEER = REPO / "tests" / "mavlink_peer.py"
WAIT_S = 60.0
DT = 1.0 / 30.0
T0 = 1000.0
S = math.sqrt(0.5)
R_W_C = Rotation.from_euler("z", 90, degrees=True).as_matrix() @ MOUNT_R_B_C["forward"]  # nose east
F32 = dict(rel=1e-6, abs=1e-9)


def start_peer(connect: str, *extra: str) -> JsonLinesProcess:
    peer = JsonLinesProcess(python_script(PEER, connect, *extra))
    peer.wait_for(lambda lines: any(m.get("ready") for m in lines), WAIT_S, "peer ready")
    return peer


def msgs(peer: JsonLinesProcess, kind: str) -> list[dict]:
    return peer.of_type(kind, key="mavpackettype")


def count(kind: str, n: int):
    return lambda lines: sum(m.get("mavpackettype") == kind for m in lines) >= n


def answers(peer: JsonLinesProcess) -> list[dict]:
    """Our answers to the peer's TIMESYNC requests (not our own requests, tc1 = 0)."""
    return [m for m in msgs(peer, "TIMESYNC") if m["tc1"] != 0]


def scenario() -> list[tuple[bool, int, float, int]]:
    """(trusted, tracker reset_counter, x [m], quality) per frame at 30 Hz."""
    rows = [(False, 0, 0.0, 0)] * 2  # 0-1 initialising
    rows += [(True, 0, 0.03 * i, 60) for i in range(8)]  # 2-9 tracking, 0.9 m/s north
    rows += [(False, 0, 0.0, 0)] * 3  # 10-12 lost
    rows += [(True, 1, 1.0 + 0.03 * i, 60) for i in range(6)]  # 13-18 restarted
    rows += [(True, 1, 3.0 + 0.03 * i, 60) for i in range(6)]  # 19-24 jump of 1.85 m
    rows += [(True, 1, 3.2, 10)] * 3  # 25-27 degraded
    rows += [(True, 1, 3.2, 60)] * 3  # 28-30 back
    return rows


def results():
    for i, (trusted, rc, x, quality) in enumerate(scenario()):
        state = TrackState.INITIALIZING if i < 2 else None
        yield i, track_result(T0 + i * DT, [x, 2.0, -1.5], R_W_C, trusted=trusted,
                              reset_counter=rc, quality=quality, state=state,
                              lost_reason="correlation peak too weak")


@pytest.fixture(scope="module")
def odometry_run() -> JsonLinesProcess:
    """The scenario through ODOMETRY, with the peer asking for TIMESYNC."""
    port = free_port()
    peer = start_peer(f"udpin:127.0.0.1:{port}", "--timesync-s", "0.05")
    cfg = MavlinkConfig(enabled=True, connect=f"udpout:127.0.0.1:{port}", stale_s=30.0,
                        queue_frames=100, set_origin=True, set_home=True,
                        origin_lat_deg=47.3977419, origin_lon_deg=8.5455938, origin_alt_m=488.5)
    out = MavlinkOutput(cfg)
    try:
        for _i, r in results():
            out.publish(r)
        n_poses = sum(row[0] for row in scenario())
        peer.wait_for(count("ODOMETRY", n_poses), WAIT_S, "every pose")
        peer.wait_for(lambda lines: len([m for m in lines if m.get("mavpackettype") == "TIMESYNC"
                                         and m["tc1"] != 0]) >= 6, WAIT_S, "timesync replies")
        peer.wait_for(count("SET_HOME_POSITION", 1), WAIT_S, "home")
        assert out.stats()["dropped"] == 0
    finally:
        out.close()
        peer.stop()
    return peer


def test_one_odometry_per_tracked_frame_in_order(odometry_run: JsonLinesProcess) -> None:
    odo = msgs(odometry_run, "ODOMETRY")
    tracked = [i for i, row in enumerate(scenario()) if row[0]]
    assert [m["time_usec"] for m in odo] == [round((T0 + i * DT) * 1e6) for i in tracked]
    for m in odo:
        assert (m["src_system"], m["src_component"]) == (1, 197)
        assert (m["frame_id"], m["child_frame_id"], m["estimator_type"]) == (20, 12, 3)


def test_odometry_pose_quaternion_and_covariance(odometry_run: JsonLinesProcess) -> None:
    odo = msgs(odometry_run, "ODOMETRY")
    tracked = [row for row in scenario() if row[0]]
    for m, (_t, _rc, x, quality) in zip(odo, tracked):
        assert (m["x"], m["y"], m["z"]) == (pytest.approx(x, **F32), 2.0, -1.5)
        assert m["q"] == pytest.approx([S, 0.0, 0.0, S], abs=1e-7)  # w first, body yawed 90
        cov = m["pose_covariance"]
        assert [i for i, v in enumerate(cov) if v != 0] == [0, 6, 11, 15, 18, 20]
        assert [cov[i] for i in (0, 6, 11, 15, 18, 20)] == pytest.approx(list(POSE_VAR), rel=1e-6)
        assert m["quality"] == quality


def test_odometry_velocity_is_body_frd(odometry_run: JsonLinesProcess) -> None:
    odo = msgs(odometry_run, "ODOMETRY")
    firsts = {0, 8, 14}  # first pose after start, after the lost spell, after the jump
    for k, m in enumerate(odo):
        v = [m["vx"], m["vy"], m["vz"]]
        if k in firsts:
            assert all(math.isnan(c) for c in v) and math.isnan(m["velocity_covariance"][0])
        elif k < 20:  # moving 0.9 m/s north, facing east: to the body's left
            assert v == pytest.approx([0.0, -0.9, 0.0], abs=1e-5)
            vc = m["velocity_covariance"]
            assert [i for i, c in enumerate(vc) if c != 0] == [0, 6, 11, 15, 18, 20]
        rates = [m["rollspeed"], m["pitchspeed"], m["yawspeed"]]
        if k not in firsts:
            assert rates == pytest.approx([0.0, 0.0, 0.0], abs=1e-6)


def test_reset_counter_bumps_exactly_on_resets(odometry_run: JsonLinesProcess) -> None:
    counters = [m["reset_counter"] for m in msgs(odometry_run, "ODOMETRY")]
    c0 = counters[0]  # one above an earlier process's last (test_restart_* checks it)
    # 8 poses, lost -> restart (tracker reset): +1 for 6 poses, jump: +1 for the rest
    assert counters == [c0] * 8 + [(c0 + 1) % 256] * 6 + [(c0 + 2) % 256] * 12


def test_no_pose_while_lost_or_initialising(odometry_run: JsonLinesProcess) -> None:
    untrusted = {round((T0 + i * DT) * 1e6) for i, row in enumerate(scenario()) if not row[0]}
    assert not untrusted & {m["time_usec"] for m in msgs(odometry_run, "ODOMETRY")}


def test_heartbeat_component_type_and_status(odometry_run: JsonLinesProcess) -> None:
    beats = msgs(odometry_run, "HEARTBEAT")
    for b in beats:
        assert (b["src_system"], b["src_component"]) == (1, 197)
        assert (b["type"], b["autopilot"]) == (18, 8)  # ONBOARD_CONTROLLER, INVALID
    states = [b["system_status"] for b in beats]
    changes = [s for k, s in enumerate(states) if k == 0 or s != states[k - 1]]
    # BOOT, STANDBY, ACTIVE, FLIGHT_TERMINATION, ACTIVE, CRITICAL, ACTIVE
    assert changes == [1, 3, 4, 8, 4, 5, 4]


def test_statustext_on_every_state_change(odometry_run: JsonLinesProcess) -> None:
    texts = [m["text"] for m in msgs(odometry_run, "STATUSTEXT")]
    c0 = msgs(odometry_run, "ODOMETRY")[0]["reset_counter"]
    assert texts == [
        "NISLAM: initialising",
        "NISLAM: tracking, quality 60",
        "NISLAM: lost: correlation peak too weak",
        f"NISLAM: reset {(c0 + 1) % 256}: lost",
        "NISLAM: tracking, quality 60",
        f"NISLAM: reset {(c0 + 2) % 256}: jump 1.85 m",
        "NISLAM: degraded, quality 10",
        "NISLAM: tracking, quality 60",
    ]
    severities = [m["severity"] for m in msgs(odometry_run, "STATUSTEXT")]
    assert severities == [6, 6, 2, 5, 6, 5, 4, 6]


def test_timesync_answered_with_our_monotonic_clock(odometry_run: JsonLinesProcess) -> None:
    replies = answers(odometry_run)
    assert replies
    for m in replies:
        # ts1 echoes the request, stamped by the peer (time.monotonic_ns) when
        # it sent it; tc1 is our clock when we answered; "t" the peer's clock
        # when the answer arrived. One CLOCK_MONOTONIC on this host, so they
        # come in this order, however long each step took.
        assert 0 < m["ts1"] <= m["tc1"] <= round(m["t"] * 1e9)


def test_origin_and_home_from_config(odometry_run: JsonLinesProcess) -> None:
    origin = msgs(odometry_run, "SET_GPS_GLOBAL_ORIGIN")[0]
    assert (origin["target_system"], origin["latitude"], origin["longitude"],
            origin["altitude"]) == (1, 473977419, 85455938, 488500)
    home = msgs(odometry_run, "SET_HOME_POSITION")[0]
    assert (home["latitude"], home["longitude"], home["altitude"]) == (473977419, 85455938,
                                                                       488500)
    assert home["q"] == [1.0, 0.0, 0.0, 0.0]


def test_vision_position_fallback() -> None:
    port = free_port()
    peer = start_peer(f"udpin:127.0.0.1:{port}")
    out = MavlinkOutput(MavlinkConfig(connect=f"udpout:127.0.0.1:{port}",
                                      message="vision_position", stale_s=30.0))
    try:
        for i in range(5):
            out.publish(track_result(T0 + i * DT, [0.03 * i, 2.0, -1.5], R_W_C))
        peer.wait_for(count("VISION_SPEED_ESTIMATE", 4), WAIT_S, "speed estimates")
    finally:
        out.close()
        peer.stop()
    assert not msgs(peer, "ODOMETRY")
    pos = msgs(peer, "VISION_POSITION_ESTIMATE")
    assert [m["usec"] for m in pos] == [round((T0 + i * DT) * 1e6) for i in range(5)]
    for m in pos:
        assert [m["roll"], m["pitch"], m["yaw"]] == pytest.approx([0.0, 0.0, math.pi / 2])
        assert [m["covariance"][i] for i in (0, 6, 11, 15, 18, 20)] == pytest.approx(
            list(POSE_VAR), rel=1e-6)
        assert m["reset_counter"] == pos[0]["reset_counter"]
    for m in msgs(peer, "VISION_SPEED_ESTIMATE"):  # local (NED-like) frame
        assert [m["x"], m["y"], m["z"]] == pytest.approx([0.9, 0.0, 0.0], abs=1e-5)
        assert [i for i, c in enumerate(m["covariance"]) if c != 0] == [0, 4, 8]


def test_heartbeat_at_the_configured_rate_and_stale_feed_lost() -> None:
    port = free_port()
    peer = start_peer(f"udpin:127.0.0.1:{port}")
    period_s = 0.5
    t0 = time.monotonic()
    out = MavlinkOutput(MavlinkConfig(connect=f"udpout:127.0.0.1:{port}", stale_s=0.3,
                                      heartbeat_period_s=period_s))
    try:
        out.publish(track_result(T0, [0, 0, 0]))
        peer.wait_for(lambda lines: any(m.get("text", "").startswith("NISLAM: lost: no frames")
                                        for m in lines), WAIT_S, "lost after silence")
        # While nothing changes, the heartbeats go on: four more after LOST.
        peer.wait_for(lambda lines: sum(m.get("mavpackettype") == "HEARTBEAT"
                                        and m["system_status"] == 8 for m in lines) >= 5,
                      WAIT_S, "periodic heartbeats")
    finally:
        out.close(WAIT_S)  # the sender thread has ended when elapsed_s is taken
        elapsed_s = time.monotonic() - t0
        peer.stop()
    beats = msgs(peer, "HEARTBEAT")
    states = [b["system_status"] for b in beats]
    print(f"{len(beats)} heartbeats in {elapsed_s:.2f} s (period {period_s} s); peer receive "
          f"gaps {np.round(np.diff([b['t'] for b in beats]), 2).tolist()}")
    # BOOT at the link's start, ACTIVE and LOST at once (state changes), each
    # state's heartbeats together, then LOST again and again.
    assert [s for k, s in enumerate(states) if k == 0 or s != states[k - 1]] == [1, 4, 8]
    assert states.count(8) >= 5
    # The period is kept, never shortened: a periodic heartbeat waits a whole
    # period after the previous one, so over the sender's lifetime there are
    # at most lifetime / period of them besides the three state changes
    # (a busy machine only makes fewer; a heartbeat per loop turn fails).
    sent = out.stats()["heartbeats"]
    assert len(beats) <= sent <= 3 + elapsed_s / period_s + 1


def test_tcp_link_that_goes_away_is_reopened(caplog: pytest.LogCaptureFixture) -> None:
    """No peer at first (errors counted, logged once), then a peer, then it
    goes away and comes back: the feed resumes each time, publish never waits."""
    caplog.set_level(logging.WARNING, logger="onboard.outputs.mavlink")
    port = free_port(socket.SOCK_STREAM)
    out = MavlinkOutput(MavlinkConfig(connect=f"tcp:127.0.0.1:{port}", reconnect_s=0.1,
                                      stale_s=30.0))
    stop = threading.Event()
    published = [0]

    def feed() -> None:
        while not stop.is_set():
            i = published[0]
            out.publish(track_result(T0 + i * DT, [0.001 * i, 0, 0]))
            published[0] = i + 1
            stop.wait(0.02)  # the camera's pace

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        deadline = time.monotonic() + WAIT_S
        while out.stats()["link_errors"] < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert out.stats()["link_errors"] >= 3 and not out.stats()["link_up"]
        for _round in range(2):
            peer = start_peer(f"tcpin:127.0.0.1:{port}")
            peer.wait_for(count("ODOMETRY", 5), WAIT_S, "poses over tcp")
            peer.stop()
    finally:
        stop.set()
        feeder.join(WAIT_S)
        out.close(WAIT_S)
    assert not feeder.is_alive()
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    failed = [w for w in warnings if "retrying every" in w]
    reopened = [w for w in warnings if "open again" in w]
    assert len(reopened) == 2 and 2 <= len(failed) <= 3, warnings  # one per spell
    # Every result published is accounted for: sent, found the link down, or
    # dropped from the full queue; nothing is lost silently.
    s = out.stats()
    assert s["results"] + s["dropped"] == published[0], s
    assert s["poses_sent"] + s["not_sent"] == s["results"], s


class BlockingConnect:
    """mavutil stand-in whose connections hang in their open until released:
    a TCP connect or a serial open that takes its time."""

    def __init__(self, real) -> None:
        self.mavlink = real.mavlink
        self.entered = threading.Event()
        self.release = threading.Event()

    def mavlink_connection(self, *args, **kwargs):
        self.entered.set()
        self.release.wait(WAIT_S)
        raise OSError("connection timed out")


def test_publish_never_waits_for_the_link(monkeypatch: pytest.MonkeyPatch) -> None:
    """publish() returns while the sender thread is stuck opening the link:
    the loop never waits on a socket or a serial port."""
    import onboard.outputs.mavlink as mavlink_out

    fake = BlockingConnect(mavlink_out.load_mavutil())
    monkeypatch.setattr(mavlink_out, "load_mavutil", lambda: fake)
    out = MavlinkOutput(MavlinkConfig(connect="tcp:127.0.0.1:9", queue_frames=4))
    try:
        assert fake.entered.wait(WAIT_S)  # the sender is inside the open now
        done = threading.Event()

        def publish_all() -> None:
            for i in range(10):
                out.publish(track_result(T0 + i * DT, [0.0, 0.0, 0.0]))
            done.set()

        threading.Thread(target=publish_all, daemon=True).start()
        assert done.wait(WAIT_S)  # would time out if publish() waited for the sender
        assert not fake.release.is_set()  # ... which is still stuck
        assert out.stats()["dropped"] == 6  # the queue holds 4; the oldest went, counted
    finally:
        fake.release.set()
        out.close(WAIT_S)


def test_feed_over_a_shared_autopilot_link() -> None:
    """One link per autopilot: the feed sends through drivers.fc_link.FcLink
    (which the autopilot attitude source reads too) and answers the TIMESYNC
    requests its reader thread hands over."""
    fc_link = pytest.importorskip("drivers.fc_link")
    port = free_port()
    peer = start_peer(f"udpin:127.0.0.1:{port}", "--timesync-s", "0.05")
    link = fc_link.FcLink(f"udpout:127.0.0.1:{port}", source_system=1, source_component=197)
    link.start()
    out = None
    try:
        assert link.connected.wait(WAIT_S)
        out = MavlinkOutput(MavlinkConfig(connect="unused:0", stale_s=30.0), link=link)
        for i in range(5):
            out.publish(track_result(T0 + i * DT, [0.03 * i, 2.0, -1.5], R_W_C))
        peer.wait_for(count("ODOMETRY", 5), WAIT_S, "poses over the shared link")
        peer.wait_for(lambda lines: sum(m.get("mavpackettype") == "TIMESYNC" and m["tc1"] != 0
                                        for m in lines) >= 2, WAIT_S, "timesync over the link")
        assert out.stats()["timesync_answers"] >= 1  # ours, answered through the reader
    finally:
        if out is not None:
            out.close()
        link.stop()
        peer.stop()
    odo = msgs(peer, "ODOMETRY")
    assert [m["time_usec"] for m in odo] == [round((T0 + i * DT) * 1e6) for i in range(5)]
    assert odo[0]["q"] == pytest.approx([S, 0.0, 0.0, S], abs=1e-7)
    assert msgs(peer, "HEARTBEAT")[0]["system_status"] == 1
    ours = [m for m in msgs(peer, "TIMESYNC") if m["tc1"] == 0]  # our own requests
    assert ours and all(m["ts1"] > 0 for m in ours)
