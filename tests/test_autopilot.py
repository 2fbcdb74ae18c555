"""Autopilot attitude over the flight-controller link: the boot-time mapping,
the link's hooks and reconnects, and the whole source against a pymavlink
autopilot peer in another process on 127.0.0.1 (tests/peers/mavlink_autopilot.py)."""

from __future__ import annotations

import math
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from subproc import LinePeer

from drivers.autopilot_attitude import AutopilotAttitude, BootClock
from drivers.fc_link import FcLink
from onboard.core.attitude import AttitudeBuffer

PEER = Path(__file__).resolve().parent / "peers" / "mavlink_autopilot.py"
WAIT_S = 60.0
YAW_RATE = 0.5  # rad/s, as the peer


# --------------------------------------------------------------------------- boot clock


def test_boot_clock_takes_the_least_delayed_message() -> None:
    clock = BootClock(window_s=10.0)
    origin = 5_000_000_000  # our clock when the autopilot booted
    delays_ms = [7.0, 3.0, 12.0, 1.0, 4.0, 9.0]
    for i, d in enumerate(delays_ms):
        boot_ms = 1000.0 + 20 * i
        t = clock.to_host_ns(boot_ms, origin + int((boot_ms + d) * 1e6))
    assert clock.offset_ns == origin + 1_000_000  # min delay 1 ms
    assert t == origin + int(boot_ms * 1e6) + 1_000_000


def test_boot_clock_follows_drift_and_reboots() -> None:
    clock = BootClock(window_s=1.0)
    origin = 0
    # The autopilot's crystal runs 100 ppm slow: offsets grow; old minima expire.
    for i in range(500):
        boot_ms = 20.0 * i
        arrival = origin + int(boot_ms * 1e6 * (1 + 1e-4)) + 2_000_000
        clock.to_host_ns(boot_ms, arrival)
    expected = int(20.0 * 499 * 1e6 * 1e-4) + 2_000_000
    assert abs(clock.offset_ns - expected) < 300_000  # within a 1 s window's drift (0.1 ms)
    # Reboot: time_boot_ms restarts near 0 much later.
    t = clock.to_host_ns(50.0, 100_000_000_000)
    assert clock.resets == 1 and t == 100_000_000_000


# --------------------------------------------------------------------------- link hooks


class FakeMav:
    def __init__(self) -> None:
        self.sent: list[tuple] = []

    def command_long_send(self, *args) -> None:
        self.sent.append(args)


class FakeMsg:
    def __init__(self, kind: str, **fields) -> None:
        self._kind = kind
        self.__dict__.update(fields)

    def get_type(self) -> str:
        return self._kind

    def get_srcSystem(self) -> int:
        return self.__dict__.get("src", (1, 1))[0]

    def get_srcComponent(self) -> int:
        return self.__dict__.get("src", (1, 1))[1]


class FakeConnection:
    """recv_match serves scripted messages, then fails (a vanished serial port)."""

    def __init__(self, messages: list, fail_after: bool) -> None:
        self.mav = FakeMav()
        self.messages = list(messages)
        self.fail_after = fail_after
        self.closed = False

    def recv_match(self, blocking: bool, timeout: float):
        if self.messages:
            return self.messages.pop(0)
        if self.fail_after:
            raise OSError("device disconnected")
        time.sleep(min(timeout, 0.01))  # a real recv_match waits on select() this long
        return None

    def close(self) -> None:
        self.closed = True


def test_link_dispatches_sends_and_reconnects() -> None:
    opened: list[FakeConnection] = []
    plan = [OSError("no such device"), [FakeMsg("HEARTBEAT"), FakeMsg("BAD_DATA")], []]

    def factory(connect, **kwargs):
        step = plan.pop(0) if plan else []
        if isinstance(step, Exception):
            raise step
        conn = FakeConnection(step, fail_after=bool(plan))
        opened.append(conn)
        return conn

    link = FcLink("/dev/ttyFAKE", connection_factory=factory, reconnect_min_s=0.01,
                  reconnect_max_s=0.05)
    got: list = []
    remove = link.add_listener(lambda m, t: got.append((m.get_type(), t)), ["HEARTBEAT"])
    link.add_listener(lambda m, t: 1 / 0, ["HEARTBEAT"])  # a broken listener
    assert not link.send(lambda mav: mav.command_long_send(1))  # down: skipped
    link.start()
    try:
        assert link.counters.wait_for(lambda s: s.opens == 2, WAIT_S)
        s = link.stats
        assert s.open_failures == 1 and s.disconnects == 1 and s.bad_data == 1
        assert s.callback_errors == 1 and link.alive
        assert [k for k, _ in got] == ["HEARTBEAT"] and got[0][1] > 0
        assert link.connected.wait(WAIT_S) and link.generation == 2
        assert link.send(lambda mav: mav.command_long_send(1, 2))
        assert opened[-1].mav.sent == [(1, 2)] and opened[0].closed
        remove()
    finally:
        assert link.stop(10)  # False if the reader thread did not end
    assert opened[-1].closed and not link.alive


def test_link_reopens_a_tcp_link_the_peer_closed(capsys: pytest.CaptureFixture) -> None:
    """An autopilot (or SITL) restarting closes our TCP connection: the link
    opens a new one instead of reading the dead socket for ever (pymavlink
    only prints "EOF on TCP socket" without autoreconnect)."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(2)
    port = server.getsockname()[1]
    accepted: list[socket.socket] = []

    def serve() -> None:
        first, _ = server.accept()
        first.close()  # the autopilot went away
        accepted.append(server.accept()[0])  # ... and came back

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    link = FcLink(f"tcp:127.0.0.1:{port}", reconnect_min_s=0.05, reconnect_max_s=0.2)
    link.start()
    try:
        assert link.counters.wait_for(lambda s: s.opens >= 2, WAIT_S)
        assert link.stats.disconnects >= 1 and link.connected.wait(WAIT_S)
        t.join(WAIT_S)
        assert accepted
    finally:
        assert link.stop(10)
        server.close()
        for s in accepted:
            s.close()
    assert "EOF on TCP socket" not in capsys.readouterr().out


def test_attitude_source_maps_and_filters_messages() -> None:
    link = FcLink("udpout:127.0.0.1:9")  # never started: messages are fed by hand
    buf = AttitudeBuffer()
    src = AutopilotAttitude(link, buf.push, target_system=1, target_component=1)
    q = Rotation.from_euler("zyx", [30, 10, -5], degrees=True).as_quat()  # x, y, z, w
    att = dict(q1=q[3], q2=q[0], q3=q[1], q4=q[2])  # MAVLink: w, x, y, z
    src._on_message(FakeMsg("ATTITUDE_QUATERNION", time_boot_ms=1000, **att), 2_000_000_000)
    src._on_message(FakeMsg("ATTITUDE_QUATERNION", time_boot_ms=1020, src=(2, 1), **att),
                    2_030_000_000)  # another vehicle
    src._on_message(FakeMsg("ATTITUDE_QUATERNION", time_boot_ms=1020, src=(1, 154), **att),
                    2_030_000_000)  # a gimbal
    src._on_message(FakeMsg("COMMAND_ACK", command=511, result=0), 2_040_000_000)
    assert src.stats.samples == 1 and src.stats.ignored == 2 and src.stats.acks == 1
    sample = buf.newest()
    assert sample.t_ns == 2_000_000_000
    assert np.allclose(np.abs(np.dot(sample.q_W_B_xyzw, q)), 1.0)


# --------------------------------------------------------------------------- peer process


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Peer(LinePeer):
    """tests/peers: an autopilot on UDP whose boot clock started `boot_age_s` ago."""

    def __init__(self, port: int, boot_age_s: float) -> None:
        super().__init__([sys.executable, str(PEER), "--port", str(port),
                          "--boot-age-s", str(boot_age_s)], WAIT_S)
        ready = self.expect("ready")
        self.boot_origin_ns = int(ready.split("=")[1])


class Heard:
    """What the autopilot sent, as the link's reader thread saw it: (time_boot_ms,
    arrival ns) of every ATTITUDE_QUATERNION, through a listener of our own."""

    def __init__(self, link: FcLink) -> None:
        self.messages: list[tuple[int, int]] = []
        link.add_listener(self._on_message, ["ATTITUDE_QUATERNION"])

    def _on_message(self, msg, t_ns: int) -> None:
        self.messages.append((int(msg.time_boot_ms), t_ns))


def reference_host_stamps(messages: list[tuple[int, int]], window_s: float = 10.0,
                          reboot_jump_ms: float = 1000.0) -> list[int]:
    """The stamps BootClock must give, by brute force: boot time plus the least
    (arrival - boot time) of the messages within `window_s` before this one,
    counted from the latest reboot (time_boot_ms jumping back)."""
    stamps, since = [], 0
    for k, (boot_ms, arrival) in enumerate(messages):
        if k and boot_ms < messages[k - 1][0] - reboot_jump_ms:
            since = k
        offset = min(a - b * 1_000_000 for b, a in messages[since:k + 1]
                     if a >= arrival - window_s * 1e9)
        stamps.append(boot_ms * 1_000_000 + offset)
    return stamps


def check_samples_against_the_messages(buf: AttitudeBuffer, heard: Heard) -> list[int]:
    """Every sample is one message, stamped by the boot-clock mapping (the
    reference) and holding the yaw the peer sent for its time_boot_ms; the
    link is stopped, so both lists are complete. Returns the stamps."""
    kept: list[tuple[int, int]] = []  # (host stamp, time_boot_ms): the buffer refuses
    for t, (boot_ms, _arrival) in zip(reference_host_stamps(heard.messages), heard.messages):
        if not kept or t > kept[-1][0]:  # ... a stamp not after the newest one
            kept.append((t, boot_ms))
    samples = buf.samples_after(None)
    assert [s.t_ns for s in samples] == [t for t, _b in kept]  # none lost, none invented
    for s, (_t, boot_ms) in zip(samples, kept):
        yaw = YAW_RATE * boot_ms * 1e-3  # the peer's yaw at its (whole) ms
        q = np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])
        assert abs(np.dot(s.q_W_B_xyzw, q)) > math.cos(math.radians(0.1) / 2)
    return [t for t, _b in kept]


def test_autopilot_attitude_against_a_pymavlink_peer() -> None:
    port = free_udp_port()
    peer = Peer(port, boot_age_s=123.0)
    buf = AttitudeBuffer()
    link = FcLink(f"udpout:127.0.0.1:{port}", reconnect_min_s=0.05)
    heard = Heard(link)
    # retry_s far above any stall of this machine: the one request must do.
    src = AutopilotAttitude(link, buf.push, rate_hz=50.0, retry_s=5.0)
    link.start()
    src.start()
    try:
        # The request asks for ATTITUDE_QUATERNION every 20 ms (50 Hz), the
        # peer accepts it (it prints only accepted requests) and streams.
        assert peer.expect("interval_us") == "interval_us=20000"
        assert src.counters.wait_for(lambda s: s.acks >= 1, WAIT_S)
        t0 = time.monotonic()
        assert buf.wait_for_samples(50, WAIT_S)
        print(f"50 samples in {time.monotonic() - t0:.2f} s (requested: 50 Hz)")
        assert src.stats.requests == 1 and src.stats.nacks == 0
    finally:
        stopped = [link.stop(10), src.stop(10)]  # the link first: no message after this
        peer.close()
    assert all(stopped)
    stamps = check_samples_against_the_messages(buf, heard)
    assert len(stamps) >= 50 and src.stats.samples == len(heard.messages)
    # time_boot_ms mapped onto our clock: the peer's boot instant on the shared
    # CLOCK_MONOTONIC is known. The mapping is the least-delayed message's
    # view, so it is never before the truth (>= -1: time_boot_ms truncates to
    # whole ms); how far after depends on how busy the machine was.
    err_ms = (src.boot_clock.offset_ns - peer.boot_origin_ns) * 1e-6
    print(f"boot clock mapping: {err_ms:+.2f} ms from the truth")
    assert err_ms >= -1.0
    # The buffer slerps between the samples (two 20 ms apart, if the machine let any be).
    pairs = [(a, b) for a, b in zip(stamps, stamps[1:]) if b - a <= buf.max_gap_s * 1e9]
    assert pairs
    a, b = pairs[-1]
    assert buf.rotation_at((a + b) / 2 * 1e-9) is not None


def test_autopilot_reboot_is_followed() -> None:
    """The autopilot process restarts (a reboot): the stream stops, the source
    requests it again, the new boot clock replaces the old mapping."""
    port = free_udp_port()
    peer = Peer(port, boot_age_s=500.0)
    buf = AttitudeBuffer()
    link = FcLink(f"udpout:127.0.0.1:{port}")
    heard = Heard(link)
    src = AutopilotAttitude(link, buf.push, rate_hz=50.0, retry_s=0.3)
    link.start()
    src.start()
    try:
        assert peer.expect("interval_us") == "interval_us=20000"
        assert buf.wait_for_samples(10, WAIT_S)
        peer.close()
        peer = Peer(port, boot_age_s=2.0)  # rebooted 2 s ago
        # Re-requested without any help, with the same interval.
        assert peer.expect("interval_us") == "interval_us=20000"
        n = buf.stats.pushed
        assert buf.wait_for_samples(n + 20, WAIT_S)
        assert src.stats.clock_resets == 1 and src.stats.requests >= 2
    finally:
        stopped = [link.stop(10), src.stop(10)]  # the link first: no message after this
        peer.close()
    assert all(stopped)
    # Every sample before and after the reboot mapped as the reference says
    # (the window restarts at the reboot) and holding the peer's yaw.
    check_samples_against_the_messages(buf, heard)
    err_ms = (src.boot_clock.offset_ns - peer.boot_origin_ns) * 1e-6
    print(f"boot clock mapping after the reboot: {err_ms:+.2f} ms from the truth")
    assert err_ms >= -1.0
    # The newest sample is the rebooted autopilot's: its stamp maps near the new boot.
    newest = buf.newest()
    assert newest.t_ns - peer.boot_origin_ns >= 2e9 - 1e6


@pytest.mark.parametrize("rate_hz", [10.0])
def test_requested_interval_follows_the_rate(rate_hz: float) -> None:
    port = free_udp_port()
    peer = Peer(port, boot_age_s=1.0)
    link = FcLink(f"udpout:127.0.0.1:{port}")
    src = AutopilotAttitude(link, AttitudeBuffer().push, rate_hz=rate_hz)
    link.start()
    src.start()
    try:
        assert peer.expect("interval_us") == f"interval_us={int(1e6 / rate_hz)}"
    finally:
        assert src.stop(10) and link.stop(10)
        peer.close()
