"""Our own TIMESYNC requests: the autopilot's clock offset and the link's
round trip (onboard/outputs/mavlink_timesync.py), on paper and against a peer
process whose clock is shifted by a known amount (tests/mavlink_peer.py
--clock-shift-s); the capture-to-arrival latency it gives against the
arrival the peer measured (one host: one monotonic clock)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from fake_results import track_result
from subproc import REPO, JsonLinesProcess, free_port, python_script

from onboard.app.latency import LoopTiming, delay_advice
from onboard.outputs.mavlink import MavlinkOutput
from onboard.outputs.mavlink_timesync import BURST, BURST_PERIOD_S, PERIOD_S, TimesyncClock
from onboard.outputs.settings import MavlinkConfig

PEER = REPO / "tests" / "mavlink_peer.py"
WAIT_S = 60.0


def test_least_round_trip_answer_sets_the_offset() -> None:
    """Delays up and down the link unequal and random: the estimate is the
    offset of the least-RTT answer, so it beats the mean of all answers."""
    rng = np.random.default_rng(3)
    shift_ns = 12_345_678_901
    clock = TimesyncClock()
    now = 1_000_000_000
    errors_of_mean = []
    for _ in range(40):
        ts1 = clock.due(now)
        assert ts1 == now
        up, down = rng.exponential(4e6, 2).astype(int) + 200_000  # 0.2 ms + queueing
        tc1 = ts1 + up + shift_ns
        assert clock.on_answer(tc1, ts1, ts1 + up + down)
        errors_of_mean.append((up - down) / 2)
        now = clock.next_due_ns()
    est = clock.estimate()
    assert est is not None and est.samples == 16 and est.answers == 40
    assert abs(est.offset_ns - shift_ns) < 0.5e6  # within 0.5 ms
    assert abs(est.offset_ns - shift_ns) < abs(np.mean(errors_of_mean[-16:]))
    assert est.rtt_ns <= est.rtt_median_ns


def test_schedule_and_foreign_answers() -> None:
    clock = TimesyncClock()
    sent = []
    t = 0
    while len(sent) < BURST + 2:
        ts1 = clock.due(t)
        if ts1 is not None:
            sent.append(ts1)
        t += 1_000_000  # 1 ms steps
    gaps = np.diff(sent) / 1e9
    assert gaps[:BURST - 1] == pytest.approx(BURST_PERIOD_S, abs=1e-3)
    assert gaps[-1] == pytest.approx(PERIOD_S, abs=1e-3)
    assert not clock.on_answer(5, 123, 200)  # someone else's request
    assert not clock.on_answer(5, sent[-1], sent[-1] + 2_000_000_000)  # 2 s late
    assert clock.estimate() is None and clock.ignored == 2


@pytest.mark.parametrize("shift_s", [-3.25, 1234.56789])
def test_offset_against_a_shifted_peer_within_1ms(shift_s: float) -> None:
    port = free_port()
    peer = JsonLinesProcess(python_script(PEER, f"udpin:127.0.0.1:{port}",
                                          "--clock-shift-s", str(shift_s)))
    peer.wait_for(lambda lines: any(m.get("ready") for m in lines), WAIT_S, "peer ready")
    timing = LoopTiming()
    out = MavlinkOutput(MavlinkConfig(enabled=True, connect=f"udpout:127.0.0.1:{port}",
                                      stale_s=30.0, queue_frames=100))
    out.on_written, timing.one_way_s = timing.on_written, out.one_way_s
    try:
        deadline = time.monotonic() + WAIT_S
        # One pose every 30 ms (a camera's pace), stamped 10 ms before it
        # goes out (the tracker's time), until 12 answers have come.
        while out.stats()["timesync_answers"] < 12 or timing.arrival.n < 20:
            assert time.monotonic() < deadline, out.stats()
            out.publish(track_result(time.monotonic() - 0.010, [0.0, 0.0, -1.0]))
            time.sleep(0.03)  # the feed's pace, not a synchronisation
        est = out.timesync_estimate()
        poses_sent = out.stats()["poses_sent"]
    finally:
        out.close()
    peer.wait_for(lambda lines: sum(m.get("mavpackettype") == "ODOMETRY" for m in lines)
                  >= poses_sent, WAIT_S, "every pose")
    peer.stop()
    assert est is not None
    assert abs(est["offset_ms"] - shift_s * 1e3) < 1.0, est
    assert 0 < est["rtt_min_ms"] <= est["rtt_median_ms"]
    # Each answer's tc1 is the peer's clock: our requests got them.
    answered = [m for m in peer.of_type("TIMESYNC", key="mavpackettype") if m["tc1"] == 0]
    assert len(answered) >= 12
    # Capture -> arrival: the peer's receive time minus time_usec, on the host's
    # one monotonic clock, against ours (written + half the least round trip).
    measured = np.array([m["t"] * 1e3 - m["time_usec"] / 1e3
                         for m in peer.of_type("ODOMETRY", key="mavpackettype")])
    ours = timing.arrival.percentile(50)
    assert ours is not None and np.all(measured >= 9.9)
    assert abs(np.median(measured) - ours) < 3.0, (np.median(measured), ours)
    adv = delay_advice(timing, est)
    assert adv is not None and adv["basis"] == "arrival"
    assert 10 <= adv["VISO_DELAY_MS"] <= adv["EKF2_EV_DELAY"]
