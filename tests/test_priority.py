"""The loop's real-time priority (onboard/app/priority.py): every thread of
the process raised to SCHED_FIFO when permitted, left alone when it already
runs real-time (systemd's CPUSchedulingPolicy), one line when refused.
Raised in child processes, never in the test runner itself."""

from __future__ import annotations

import os
import resource
import subprocess
import sys

from onboard.app import priority

CHILD = """
import os, threading
from onboard.app.priority import raise_to_realtime
stop = threading.Event()
t = threading.Thread(target=stop.wait)
t.start()
print(raise_to_realtime({prio}))
later = threading.Thread(target=stop.wait)  # started after: inherits from its creator
later.start()
for tid in (threading.get_native_id(), t.native_id, later.native_id):
    print(os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority)
stop.set()
"""


def _may_use_fifo(prio: int) -> bool:
    """Root (CAP_SYS_NICE) or an RLIMIT_RTPRIO allowing `prio`."""
    soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
    return os.geteuid() == 0 or soft == resource.RLIM_INFINITY or soft >= prio


def _child(prio: int, prefix: tuple[str, ...] = ()) -> list[str]:
    proc = subprocess.run([*prefix, sys.executable, "-c", CHILD.format(prio=prio)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.splitlines()


def test_every_thread_is_raised_and_later_threads_inherit_it():
    lines = _child(7)
    fifo = f"{os.SCHED_FIFO} 7"
    if _may_use_fifo(7):
        assert lines[0] == "real-time 7"
        assert lines[1:] == [fifo, fifo, fifo]
    else:  # refused: said so, nothing changed
        assert lines[0] == "normal (real-time not permitted)"
        assert all(line == f"{os.SCHED_OTHER} 0" for line in lines[1:])


def test_zero_leaves_the_process_at_normal_priority():
    lines = _child(0)
    assert lines[0] == "normal"
    assert all(line == f"{os.SCHED_OTHER} 0" for line in lines[1:])


def test_a_policy_set_from_outside_is_kept(monkeypatch):
    """systemd's CPUSchedulingPolicy=fifo runs the process real-time before
    it starts (and its seccomp filter would refuse the call): kept as it is."""
    calls = []
    monkeypatch.setattr(priority.os, "sched_getscheduler", lambda pid: os.SCHED_FIFO)
    monkeypatch.setattr(priority.os, "sched_getparam", lambda pid: os.sched_param(3))
    monkeypatch.setattr(priority.os, "sched_setscheduler", lambda *a: calls.append(a))
    assert priority.raise_to_realtime(10) == "real-time 3 (set from outside)"
    assert calls == []


def test_refusal_is_one_line_and_normal_priority(monkeypatch, caplog):
    def refuse(*_a):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(priority.os, "sched_getscheduler", lambda pid: os.SCHED_OTHER)
    monkeypatch.setattr(priority.os, "sched_setscheduler", refuse)
    with caplog.at_level("INFO", logger="onboard.app.priority"):
        assert priority.raise_to_realtime(10) == "normal (real-time not permitted)"
    assert len(caplog.records) == 1 and "not permitted" in caplog.records[0].getMessage()
