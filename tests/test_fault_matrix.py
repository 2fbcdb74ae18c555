"""The fault matrix (tests/fault_matrix.py), a reduced set: one fault per
kind of source (the camera, the AHRS, the loop). `make faults` runs all of
them and writes the table into docs/reliability.md."""

from __future__ import annotations

import pytest
from fault_matrix import FAULTS, assert_meets_the_bar, run_matrix

# What the issue asks of every fault: the warning within 1 s of the
# detector's own threshold, recovery within 3 s of the fault clearing,
# nothing untrusted passed on, nothing recorded lost.
THRESHOLD_S = {"camera unplug": 0.0, "AHRS garbage": 0.5, "pose jump after a gap": 0.43}


@pytest.mark.parametrize("name", sorted(THRESHOLD_S))
def test_fault_is_told_within_1_s_recovers_within_3_s_and_passes_nothing_on(name, tmp_path):
    (row,) = run_matrix([name], tmp_path)
    print(row)
    assert_meets_the_bar(row, THRESHOLD_S[name])


def test_the_matrix_covers_at_least_12_faults():
    assert len(FAULTS) >= 12
