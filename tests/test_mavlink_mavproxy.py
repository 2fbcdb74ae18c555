"""MAVProxy, the ground station integrators use, as the receiving peer: run
headless, it writes a telemetry log (tlog) that we read back with pymavlink.

MAVProxy is installed by the Makefile without its dependencies (it requires
opencv-python, which clashes with our opencv-python-headless); headless it
needs only pymavlink, pyserial and numpy.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import pytest
from fake_results import track_result
from subproc import JsonLinesProcess, free_port

from onboard.outputs.mavlink import MavlinkOutput, load_mavutil
from onboard.outputs.settings import MavlinkConfig

MAVPROXY = Path(sys.executable).parent / "mavproxy.py"
N = 30
WAIT_S = 60.0
END = "end of the test feed"


def read_tlog(path: Path) -> list:
    mavutil = load_mavutil()
    log = mavutil.mavlink_connection(str(path), notimestamps=False)
    out = []
    while (m := log.recv_match()) is not None:
        if m.get_type() != "BAD_DATA":
            out.append(m)
    log.close()
    return out


def ours(msgs: list, kind: str) -> list:
    return [m for m in msgs if m.get_type() == kind and m.get_srcComponent() == 197]


def test_mavproxy_logs_the_feed(tmp_path: Path) -> None:
    if not MAVPROXY.exists():
        if os.environ.get("CI"):
            pytest.fail(f"{MAVPROXY} missing: `make test` installs it (pip install --no-deps)")
        pytest.skip("MAVProxy not installed (make .venv/bin/mavproxy.py)")
    port = free_port()
    tlog = tmp_path / "feed.tlog"
    proc = JsonLinesProcess(
        [sys.executable, str(MAVPROXY), f"--master=udpin:127.0.0.1:{port}", "--daemon",
         "--non-interactive", "--nowait", "--default-modules=link", f"--logfile={tlog}",
         f"--state-basedir={tmp_path}"],
        cwd=tmp_path,
    )
    out = None
    try:
        # MAVProxy prints "Telemetry log: ..." once its link and log are open
        proc.wait_for(lambda _: any("Telemetry log" in t for t in proc.text), WAIT_S,
                      "MAVProxy up")
        # stale_s far above any stall of this machine: the feed is never "lost"
        # between two frames. The end is a frame the tracker lost: its
        # STATUSTEXT leaves the sender after every ODOMETRY, and MAVProxy
        # prints it ("AP: NISLAM: lost: end of the test feed").
        out = MavlinkOutput(MavlinkConfig(connect=f"udpout:127.0.0.1:{port}", stale_s=WAIT_S))
        t0 = time.monotonic()
        for i in range(N):  # at the camera rate, as in flight (the queue holds 8)
            time.sleep(max(0.0, t0 + i / 30 - time.monotonic()))
            out.publish(track_result(t0 + i / 30, [0.01 * i, 0.0, 0.0], quality=70))
        out.publish(track_result(t0 + N / 30, trusted=False, lost_reason=END))
        proc.wait_for(lambda _: any(f"NISLAM: lost: {END}" in t for t in proc.text), WAIT_S,
                      "last message")
    finally:
        if out is not None:
            out.close(WAIT_S)
        proc.stop(signal.SIGTERM, WAIT_S)  # MAVProxy flushes its log as it exits (status 1)
    console = "\n".join(proc.text) + proc.stderr
    msgs = read_tlog(tlog)
    odo = ours(msgs, "ODOMETRY")
    # Every pose reached the log or was dropped from the sender's full queue
    # (a stalled machine), counted: nothing lost silently. The newest is never dropped.
    stats = out.stats()
    assert len(odo) + stats["dropped"] + stats["not_sent"] == N, (stats, console)
    published = [round((t0 + i / 30) * 1e6) for i in range(N)]
    stamps = [m.time_usec for m in odo]
    assert stamps == sorted(set(stamps)) and set(stamps) <= set(published)
    assert stamps[-1] == published[-1]
    assert {(m.frame_id, m.child_frame_id, m.estimator_type, m.quality) for m in odo} == {
        (20, 12, 3, 70)}
    assert odo[-1].x == pytest.approx(0.01 * (N - 1), rel=1e-6)
    beats = ours(msgs, "HEARTBEAT")
    assert beats and {(b.type, b.get_srcSystem()) for b in beats} == {(18, 1)}
    assert beats[0].system_status == 1 and 4 in {b.system_status for b in beats}
    texts = [m.text for m in ours(msgs, "STATUSTEXT")]
    assert any(t.startswith("NISLAM: tracking") for t in texts)
    assert texts[-1] == f"NISLAM: lost: {END}"
    # ... logged after every pose, in the order sent.
    feed = [m for m in msgs if m.get_srcComponent() == 197]
    end_at = next(k for k, m in enumerate(feed) if m.get_type() == "STATUSTEXT"
                  and m.text == f"NISLAM: lost: {END}")
    assert all(k < end_at for k, m in enumerate(feed) if m.get_type() == "ODOMETRY")
