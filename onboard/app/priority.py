"""Real-time scheduling for the loop once it runs (docs/latency.md, "Priority").

A pose is only worth its age to the autopilot's EKF. At normal priority the
loop and the camera thread wake late whenever anything else on the machine
runs: on a quiet 2-core VM the source stage's p99 was 4 ms above its median
and the capture -> pose p99 52-57 ms; at SCHED_FIFO the wake-ups are on time
(source p99 0.3 ms above its median) even beside a full load. Flight software
on Linux does the same (ArduPilot's and PX4's Linux builds run their threads
at SCHED_FIFO).

Raised by `nislam run` (Service(realtime=True): a process-wide setting is the
entry point's to ask for) once the first frame is tracked, so numba's compilation at start-up
never runs at this priority; every thread of the process is raised, and
threads started later inherit it from their creator. Needs root,
CAP_SYS_NICE or an RLIMIT_RTPRIO of at least the priority; without them the
process stays at normal priority (one line). Under systemd the unit sets the
policy itself (`CPUSchedulingPolicy=fifo`) and its seccomp filter refuses the
call: a thread already real-time is left as it is.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

log = logging.getLogger(__name__)

# How long a thread may keep the GIL while another waits for it. CPython's
# default is 5 ms: each time the loop comes back from a call that released the
# GIL (an FFT, a numba kernel, a wait for the frame) while a driver or output
# thread runs Python (pymavlink's parser, the AHRS reader, the status's JSON,
# the replay's decoder), it may wait that long. On the 30 s `circle` at 5 ms
# the tracker's wall-time p99 was 18.5-26.0 ms against a CPU-time p99 of
# 12.8-16.0 ms; at 0.5 ms, 16.0-18.3 ms (docs/latency.md, "Priority").
GIL_SWITCH_INTERVAL_S = 0.0005


def hand_gil_over_promptly() -> None:
    """The process's GIL switch interval to GIL_SWITCH_INTERVAL_S."""
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)


def _thread_ids() -> list[int]:
    try:
        return sorted(int(p.name) for p in Path("/proc/self/task").iterdir())
    except OSError:  # not Linux: only this thread
        return [0]


def raise_to_realtime(priority: int) -> str:
    """Every thread of the process to SCHED_FIFO at `priority` (0: leave
    them); what the loop now runs at, for run.json and the log."""
    if priority <= 0:
        return "normal"
    if not hasattr(os, "SCHED_FIFO"):
        return "normal (no SCHED_FIFO on this system)"
    if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
        return f"real-time {os.sched_getparam(0).sched_priority} (set from outside)"
    param = os.sched_param(priority)
    raised = 0
    for tid in _thread_ids():
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, param)
            raised += 1
        except ProcessLookupError:  # the thread ended meanwhile
            continue
        except PermissionError:
            log.info("real-time priority %d not permitted (root, CAP_SYS_NICE or "
                     "LimitRTPRIO= needed): the loop stays at normal priority", priority)
            return "normal (real-time not permitted)"
    log.info("loop at real-time priority: SCHED_FIFO %d (%d threads)", priority, raised)
    return f"real-time {priority}"
