"""The host's steal over a run (onboard/app/cpu_steal.py), from /proc/stat text."""

from __future__ import annotations

from pathlib import Path

from onboard.app.cpu_steal import CpuTicks, parse_proc_stat, read_ticks, steal_share

# A 2-CPU guest's /proc/stat head: user nice system idle iowait irq softirq
# steal guest guest_nice (guest time is already inside user and nice).
BEFORE = """cpu  2622404 5423741 789987 4420553 31017 0 23958 169369 7 3
cpu0 1311202 2711870 394993 2210276 15508 0 11979 84684 0 0
cpu1 1311202 2711871 394994 2210277 15509 0 11979 84685 0 0
intr 1 2 3
"""
AFTER = """cpu  2624839 5423741 790107 4424373 31023 0 23959 169487 9 3
cpu0 1312419 2711870 395053 2212186 15511 0 11979 84743 0 0
"""


def test_steal_share_is_the_hosts_share_of_all_cpu_time_between_readings() -> None:
    before, after = parse_proc_stat(BEFORE), parse_proc_stat(AFTER)
    # The aggregate line, its first eight columns (not cpu0's, not guest time).
    assert before == CpuTicks(steal=169369, total=2622404 + 5423741 + 789987 + 4420553
                              + 31017 + 0 + 23958 + 169369)
    # (169487 - 169369) / (2435 + 0 + 120 + 3820 + 6 + 0 + 1 + 118) = 118 / 6500
    assert steal_share(before, after) == 118 / 6500


def test_no_share_without_a_readable_steal_column_or_elapsed_time(tmp_path: Path) -> None:
    assert parse_proc_stat("cpu  1 2 3 4\n") is None  # a kernel without the column
    assert parse_proc_stat("intr 1 2\n") is None
    assert parse_proc_stat("cpu  1 2 3 4 5 6 7 x\n") is None
    ticks = parse_proc_stat(BEFORE)
    assert steal_share(ticks, ticks) is None and steal_share(None, ticks) is None
    assert read_ticks(tmp_path / "absent") is None
    assert read_ticks() is None or read_ticks().total > 0  # this machine's, when Linux
