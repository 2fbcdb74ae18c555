"""Faults outside a driver, told like a driver's (onboard/core/device_state.py):
the zenoh router gone and back (a real `nislam router` killed and restarted),
the AHRS's stamps jumping ahead or back while the camera's do not. The rows
are those of the fault matrix (tests/fault_matrix_links.py, `make faults`)."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
from fault_matrix import assert_meets_the_bar, run_matrix
from subproc import free_port

from onboard.core.attitude import AttitudeBuffer, AttitudeSample
from onboard.core.device_state import State
from onboard.outputs.group import OutputGroup
from onboard.outputs.settings import ZenohConfig

Q = (0.0, 0.0, 0.0, 1.0)


def test_jumped_stamps_are_dropped_told_once_and_never_give_a_frame_an_attitude(caplog):
    now = {"ns": 10_000_000_000}
    buf = AttitudeBuffer(now_ns=lambda: now["ns"], label="myAHRS+")
    step = 10_000_000  # 100 Hz

    def run(n: int, shift_ns: int = 0) -> None:
        for _ in range(n):
            now["ns"] += step
            buf.push(AttitudeSample(now["ns"] + shift_ns, Q))

    with caplog.at_level(logging.WARNING, logger="onboard.core.device_state"):
        run(50)
        t_good = now["ns"] * 1e-9
        run(100, shift_ns=3_000_000_000)  # 1 s of stamps 3 s ahead
        run(100, shift_ns=-3_000_000_000)  # then 1 s of stamps 3 s back
        assert buf.stamps.state is State.BAD_DATA
        t_clear = now["ns"] * 1e-9
        run(20)
    lines = [r.getMessage() for r in caplog.records]
    assert buf.stats.rejected_time_jump == 200 and buf.stats.pushed == 70
    assert len(lines) == 2, lines  # one warning for the spell (ahead, then back), one recovery
    assert "myAHRS+ stamps: bad data: time jump: stamped +3.0 s" in lines[0]
    assert "recovered" in lines[1] and buf.stamps.state is State.STREAMING
    # frames captured while the stamps were wrong get no attitude; before and after, they do
    assert all(buf.rotation_at(t) is None for t in np.arange(t_good + 0.02, t_clear, 0.033))
    assert buf.rotation_at(t_good - 0.1) is not None
    assert buf.rotation_at(now["ns"] * 1e-9 - 0.05) is not None


def test_a_replay_buffer_has_no_clock_to_check_against():
    buf = AttitudeBuffer()  # stamps on a recording's time base
    assert buf.push(AttitudeSample(5, Q)) and buf.push(AttitudeSample(10**15, Q))
    assert buf.stats.rejected_time_jump == 0


def test_a_client_without_its_router_says_so_in_the_status_devices(caplog):
    from onboard.outputs.zenoh_out import ZenohOutput

    endpoint = f"tcp/127.0.0.1:{free_port()}"  # nobody listens there
    with caplog.at_level(logging.WARNING, logger="onboard.outputs.zenoh_link"):
        out = ZenohOutput(ZenohConfig(enabled=True, mode="client", connect=(endpoint,)))
        try:
            group = OutputGroup([out])
            deadline = time.monotonic() + 20.0
            while not any(s.state.failed for s in group.device_states()):
                assert time.monotonic() < deadline, "no state for the missing router"
                time.sleep(0.05)
            (snap,) = group.device_states()
            assert snap.text().startswith("zenoh router no device (nothing answers at tcp/127")
            looks = out.link.looks + 2  # two more looks at the missing router: no more lines
            while out.link.looks < looks:
                assert time.monotonic() < deadline, "the link is no longer looked at"
                time.sleep(0.05)
        finally:
            out.close(2)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and f"zenoh router {endpoint}: no device" in lines[0], lines


def test_a_peer_that_only_listens_has_no_link_state():
    from onboard.outputs.zenoh_out import ZenohOutput

    port = free_port(__import__("socket").SOCK_STREAM)
    with ZenohOutput(ZenohConfig(enabled=True, listen=(f"tcp/127.0.0.1:{port}",))) as out:
        assert OutputGroup([out]).device_states() == []


# What the issue asks of every row: the warning within 1 s of the detector's
# own threshold, recovery within 3 s of the fault clearing, nothing passed on.
THRESHOLD_S = {"zenoh router gone": 0.25, "AHRS time jump back": 0.0}


@pytest.mark.parametrize("name", sorted(THRESHOLD_S))
def test_fault_row(name, tmp_path):
    (row,) = run_matrix([name], tmp_path)
    print(row)
    assert_meets_the_bar(row, THRESHOLD_S[name])
