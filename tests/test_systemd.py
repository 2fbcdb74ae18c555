"""The systemd unit: it verifies cleanly, its hardening scores, and the
notify sender speaks the protocol on path and abstract sockets."""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
from pathlib import Path

import pytest
from subproc import REPO

from onboard.app.sdnotify import Notifier

UNIT = REPO / "systemd" / "nislam.service"
NISLAM = REPO / ".venv" / "bin" / "nislam"
SYSTEMD_ANALYZE = shutil.which("systemd-analyze")
needs_systemd = pytest.mark.skipif(SYSTEMD_ANALYZE is None,
                                   reason="systemd-analyze is not installed on this machine")


def unit_copy(tmp_path: Path) -> Path:
    """The unit with ExecStart on this checkout's nislam (verify checks it exists)."""
    text = UNIT.read_text()
    text, n = re.subn(r"^ExecStart=\S+", f"ExecStart={NISLAM}", text, flags=re.M)
    assert n == 1
    path = tmp_path / "nislam.service"
    path.write_text(text)
    return path


@needs_systemd
def test_unit_verifies_with_empty_stderr(tmp_path: Path) -> None:
    proc = subprocess.run([SYSTEMD_ANALYZE, "verify", str(unit_copy(tmp_path))],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr


@needs_systemd
def test_unit_exposure_score_is_at_most_4(tmp_path: Path) -> None:
    proc = subprocess.run(
        [SYSTEMD_ANALYZE, "security", "--offline=true", "--threshold=40", "--no-pager",
         str(unit_copy(tmp_path))], capture_output=True, text=True, timeout=60)
    score = re.search(r"Overall exposure level for \S+: (\d+\.\d+)", proc.stdout)
    assert score is not None, proc.stdout[-2000:] + proc.stderr
    assert float(score.group(1)) <= 4.0 and proc.returncode == 0


def test_unit_keeps_serial_usb_and_network_open() -> None:
    """Hardening must not take away what the drone needs."""
    text = UNIT.read_text()
    keys = [line.split("=", 1) for line in text.splitlines() if "=" in line
            and not line.startswith("#")]
    values: dict[str, list[str]] = {}
    for k, v in keys:
        values.setdefault(k, []).append(v)
    assert values["Type"] == ["notify"] and values["Restart"] == ["on-failure"]
    assert "PrivateDevices" not in values and "PrivateNetwork" not in values
    assert "dialout" in values["SupplementaryGroups"][0]
    allowed = " ".join(values["DeviceAllow"])
    assert "char-usb_device" in allowed and "char-ttyACM" in allowed
    families = values["RestrictAddressFamilies"][0].split()
    assert {"AF_INET", "AF_INET6", "AF_UNIX", "AF_NETLINK"} <= set(families)
    # the loop's latency: real-time priority set by systemd, below IRQ threads
    assert values["CPUSchedulingPolicy"] == ["fifo"]
    assert 1 <= int(values["CPUSchedulingPriority"][0]) < 50
    rule = (REPO / "systemd" / "80-nislam-oakd.rules").read_text()
    assert 'ATTRS{idVendor}=="03e7"' in rule


@pytest.mark.parametrize("abstract", [False, True])
def test_notifier_sends_ready_status_watchdog_and_stopping(tmp_path: Path, abstract: bool) -> None:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    if abstract:
        name = f"nislam-test-{os.getpid()}"
        sock.bind("\0" + name)
        env_socket = "@" + name
    else:
        env_socket = str(tmp_path / "notify.sock")
        sock.bind(env_socket)
    sock.settimeout(5)
    now = [100.0]
    n = Notifier({"NOTIFY_SOCKET": env_socket, "WATCHDOG_USEC": "2000000"}, clock=lambda: now[0])
    assert n.enabled and n.watchdog_period_s == 2.0
    n.ready("up")
    assert sock.recv(256) == b"READY=1\nSTATUS=up"
    n.watchdog()
    n.watchdog()  # within half the period: not sent
    now[0] += 1.0
    n.watchdog()
    n.status("tracking 30 Hz")
    n.stopping()
    got = [sock.recv(256) for _ in range(4)]
    assert got == [b"WATCHDOG=1", b"WATCHDOG=1", b"STATUS=tracking 30 Hz", b"STOPPING=1"]
    assert n.sent == {"READY": 1, "WATCHDOG": 2, "STATUS": 1, "STOPPING": 1}
    n.close()
    sock.close()


def test_notifier_outside_systemd_and_for_another_pid_does_nothing() -> None:
    assert not Notifier({}).enabled
    other = Notifier({"WATCHDOG_USEC": "1000000", "WATCHDOG_PID": str(os.getpid() + 1)})
    assert other.watchdog_period_s is None
    other.watchdog()
    assert other.sent == {}
