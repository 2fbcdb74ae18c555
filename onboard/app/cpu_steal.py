"""The share of the CPUs' time a virtual machine's host gave to others during a
run (the `steal` column of Linux's /proc/stat), for run.json and the summary.

A guest's threads do not run while the host has their virtual CPU elsewhere,
and neither their CPU time nor anything inside the process can tell. On the
2-core VM the tests and benchmarks run on, the 30 s `circle` (the issue's
acceptance command, stop 30) read latency p99 49.4 / 51.3 / 63.3 ms at 0.9 /
1.9 / 3.3 % steal, with the tracker's CPU-time p99 the same in all three
(12.2-14.3 ms): a latency figure from a VM means little without it.
docs/latency.md, "Priority".
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

PROC_STAT = Path("/proc/stat")


@dataclass(frozen=True)
class CpuTicks:
    """All CPUs' time since boot in clock ticks: the host's steal and the total."""

    steal: int
    total: int


def parse_proc_stat(text: str) -> CpuTicks | None:
    """The aggregate `cpu` line of /proc/stat: user nice system idle iowait irq
    softirq steal (guest and guest_nice are already inside user and nice).
    None without a `cpu` line or the steal column (kernels before 2.6.11)."""
    for line in text.splitlines():
        fields = line.split()
        if fields and fields[0] == "cpu":
            if len(fields) < 9:
                return None
            try:
                ticks = [int(f) for f in fields[1:9]]
            except ValueError:
                return None
            return CpuTicks(steal=ticks[7], total=sum(ticks))
    return None


def read_ticks(path: Path = PROC_STAT) -> CpuTicks | None:
    """The ticks now; None where there is no /proc/stat (not Linux)."""
    try:
        return parse_proc_stat(path.read_text())
    except OSError:
        return None


def steal_share(before: CpuTicks | None, after: CpuTicks | None) -> float | None:
    """The share (0-1) of the CPUs' time between two readings that the host
    stole; None when either is missing or no time passed."""
    if before is None or after is None or after.total <= before.total:
        return None
    return (after.steal - before.steal) / (after.total - before.total)
