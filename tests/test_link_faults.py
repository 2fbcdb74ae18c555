"""Faults outside a driver, told like a driver's (onboard/core/device_state.py):
the zenoh router gone and back (a real `nislam router` killed and restarted).
The rows are those of the fault matrix (tests/fault_matrix_links.py, `make
faults`)."""

from __future__ import annotations

import logging
import time

import pytest
from fault_matrix import run_matrix
from subproc import free_port

from onboard.outputs.group import OutputGroup
from onboard.outputs.settings import ZenohConfig


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
            time.sleep(0.6)  # more polls: no more lines
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
THRESHOLD_S = {"zenoh router gone": 0.25}


@pytest.mark.parametrize("name", sorted(THRESHOLD_S))
def test_fault_row(name, tmp_path):
    (row,) = run_matrix([name], tmp_path)
    print(row)
    assert row.warn_s <= THRESHOLD_S[name] + 1.0
    assert row.recover_s <= 3.0
    assert row.passed_on == 0
    assert row.lost == "none"
