"""myAHRS+ driver: protocol checks, then the driver over a real pseudo-terminal
against a simulated device process (tests/peers/myahrs_device.py) with
checksum errors, partial lines, garbage, silence and unplug/replug behind a
stable symlink."""

from __future__ import annotations

import math
import os
import queue
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from drivers.myahrs import MyAhrsDriver, MyAhrsParser, checksum, command, startup_commands
from onboard.core.attitude import AttitudeBuffer

DEVICE = Path(__file__).resolve().parent / "peers" / "myahrs_device.py"
WAIT_S = 60.0  # generous: a busy 2-core CI machine


# --------------------------------------------------------------------------- protocol


def test_checksum_matches_the_reference_examples() -> None:
    # flight-stack doc §9: "@version*3A"; the user guide's data examples.
    assert command("version") == b"@version*3A\r\n"
    rpyimu = (b"$RPYIMU,39,0.42,-0.31,-26.51,-0.0049,-0.0038,-1.0103,-0.0101,0.0014,"
              b"-0.4001,51.9000,26.7000,11.7000,41.5")
    assert checksum(rpyimu) == "1F"
    quatimu = (b"$QUATIMU,30,-0.1417,-0.0503,0.6582,0.7377,0.0863,0.2696,-0.8973,-0.3619,"
               b"0.4495,-0.1696,13.8000,11.1000,-95.1000,42.1")
    assert checksum(quatimu) == "78"


def test_startup_commands() -> None:
    cmds = startup_commands(4)
    assert [c.split(b"*")[0] for c in cmds] == [b"@mode,AC", b"@asc_out,QUATIMU", b"@divider,4"]
    for c in cmds:
        body, sent = c[:-2].split(b"*")
        assert checksum(body).encode() == sent and c.endswith(b"\r\n")


QUATIMU = (b"$QUATIMU,30,-0.1417,-0.0503,0.6582,0.7377,0.0863,0.2696,-0.8973,-0.3619,"
           b"0.4495,-0.1696,13.8000,11.1000,-95.1000,42.1*78\r\n")


def test_parser_reads_a_sentence_scalar_last() -> None:
    p = MyAhrsParser()
    (s,) = p.feed(QUATIMU, 123)
    assert s.t_ns == 123 and s.seq == 30
    assert s.q_xyzw == (-0.1417, -0.0503, 0.6582, 0.7377)  # x, y, z, w as sent
    assert s.accel_g == (0.0863, 0.2696, -0.8973) and s.gyro_dps == (-0.3619, 0.4495, -0.1696)
    assert s.temperature_c == 42.1
    assert p.stats.sentences == 1


def test_parser_stamps_a_split_line_with_its_first_byte() -> None:
    p = MyAhrsParser()
    assert p.feed(QUATIMU[:20], 1000) == []
    (s,) = p.feed(QUATIMU[20:], 5000)
    assert s.t_ns == 1000


def test_parser_counts_and_skips_faults() -> None:
    p = MyAhrsParser()
    bad_sum = QUATIMU.replace(b"*78", b"*79")
    no_sum = QUATIMU.replace(b"*78", b"")
    partial = QUATIMU[:40]
    garbage = b"\x00\x07hello\xff\r\n"
    reply_ok = command("mode,AC").replace(b"@", b"~")  # checksum recomputed below
    body = b"~mode,OK,mode=AC"
    reply_ok = body + b"*" + checksum(body).encode() + b"\r\n"
    body = b"~divider,ERROR"
    reply_err = body + b"*" + checksum(body).encode() + b"\r\n"
    body = b"$RPY,68,0.04,1.56,34.22"
    rpy = body + b"*" + checksum(body).encode() + b"\r\n"
    body = b"$QUATIMU,1,a,b"
    malformed = body + b"*" + checksum(body).encode() + b"\r\n"
    stream = (bad_sum + no_sum + partial + QUATIMU + garbage + reply_ok + reply_err + rpy
              + malformed + b"$" + b"9" * 400 + QUATIMU)
    samples = p.feed(stream, 7)
    s = p.stats
    assert len(samples) == 2 and s.sentences == 2
    assert s.checksum_errors == 2
    assert s.partial_lines == 2  # cut off by a new '$', and the overlong line
    assert s.garbage_lines == 1 and s.garbage_bytes == 8
    assert s.replies == 2 and s.reply_errors == 1 and p.last_reply == "~divider,ERROR"
    assert s.other_sentences == 1 and s.malformed == 1
    p.feed(QUATIMU[:30], 8)
    p.reset()  # connection lost mid-sentence
    assert p.stats.partial_lines == 3


# --------------------------------------------------------------------------- device process


class DeviceProcess:
    """The simulated myAHRS+ in its own process; its stdout lines in a queue."""

    def __init__(self, link: Path) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, str(DEVICE), "--link", str(link)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1)
        self.lines: queue.Queue[str] = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(line.strip())

    def expect(self, prefix: str, timeout_s: float = WAIT_S) -> str:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                line = self.lines.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(f"device never said {prefix!r}") from None
            if line.startswith(prefix):
                return line

    def send(self, text: str, reply: str | None = None) -> str | None:
        self.proc.stdin.write(text + "\n")
        self.proc.stdin.flush()
        return self.expect(reply) if reply else None

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self.send("quit")
                self.proc.wait(10)
            except (BrokenPipeError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(10)


@pytest.fixture()
def device(tmp_path: Path):
    link = tmp_path / "myahrs"
    dev = DeviceProcess(link)
    dev.expect("plugged")
    dev.link = link
    yield dev
    dev.close()


def start_driver(device: DeviceProcess, **kwargs) -> tuple[MyAhrsDriver, AttitudeBuffer, list]:
    """The driver on the device's link. Silence handling is off unless a test
    asks for it (silence_s): a stall of this machine must not look like a
    device that forgot its settings."""
    buf = AttitudeBuffer()
    readings: list = []
    kwargs = {"silence_s": 10 * WAIT_S, "reopen_after_s": 20 * WAIT_S, **kwargs}
    drv = MyAhrsDriver(str(device.link), buf.push, reconnect_min_s=0.05, reconnect_max_s=0.5,
                       on_reading=readings.append, **kwargs)
    drv.start()
    return drv, buf, readings


def wait_samples(buf: AttitudeBuffer, more: int) -> None:
    target = buf.stats.pushed + more
    assert buf.wait_for_samples(target, WAIT_S), f"samples stuck at {buf.stats.pushed}"


def wait_fresh_attitude(buf: AttitudeBuffer) -> bool:
    """True once a frame captured from now on gets an attitude: the AHRS
    passes the present with samples close enough together to interpolate
    between. Checked as each sample arrives, up to WAIT_S."""
    t_frame = time.monotonic()
    deadline = t_frame + WAIT_S
    while time.monotonic() < deadline:
        if buf.rotation_at(t_frame) is not None:
            return True
        buf.wait_covered(t_frame, max(0.0, deadline - time.monotonic()))
    return False


def test_driver_configures_the_device_and_reads_samples(device) -> None:
    started_ns = time.monotonic_ns()
    drv, buf, readings = start_driver(device, divider=2, latency_ms=5.0)
    try:
        # The divider asked for (100 Hz / 2 = 50 Hz) is the one the device took.
        assert device.expect("configured") == "configured divider=2"
        t0 = time.monotonic()
        wait_samples(buf, 20)
        print(f"20 samples in {time.monotonic() - t0:.2f} s (divider 2: 50 Hz)")
        # Values and order: sample `seq` is a yaw of seq * 0.01 rad, scalar last.
        got = list(readings)  # the driver thread keeps appending
        assert [x.seq for x in got] == list(range(len(got)))  # every sample, in order
        r = readings[-1]
        assert r.q_xyzw[2] == pytest.approx(math.sin(0.005 * r.seq), abs=1e-6)
        assert r.q_xyzw[3] == pytest.approx(math.cos(0.005 * r.seq), abs=1e-6)
        newest = buf.newest()  # (the reading after it may be in, the sample not yet)
        assert newest.t_ns + 5_000_000 in {x.t_ns for x in list(readings)}  # latency removed
        assert started_ns <= r.t_ns <= time.monotonic_ns()  # stamped on our monotonic clock
        assert wait_fresh_attitude(buf)
        s = drv.stats
        assert s.opens == 1 and s.parser.replies == 3 and s.parser.checksum_errors == 0
        assert s.parser.reply_errors == 0
    finally:
        assert drv.stop(10)


def test_driver_counts_faults_and_keeps_reading(device) -> None:
    drv, buf, readings = start_driver(device)
    try:
        device.expect("configured")
        wait_samples(buf, 10)
        for fault in ("badsum 3", "partial 2", "garbage 4"):
            device.send(fault, "injected")
            wait_samples(buf, 10)  # faults are spent before these arrive
        p = drv.stats.parser
        assert (p.checksum_errors, p.partial_lines, p.garbage_lines) == (3, 2, 4)
        assert p.malformed == 0 and drv.stats.disconnects == 0
        # Samples skip exactly the broken sentences' sequence numbers (the
        # device makes no sample while its output waits: none lost there).
        seqs = [r.seq for r in readings]
        assert seqs == sorted(seqs) and seqs[-1] - seqs[0] + 1 - len(seqs) == 5
    finally:
        assert drv.stop(10)


def test_driver_survives_silence(device) -> None:
    drv, buf, _ = start_driver(device, silence_s=0.3, reopen_after_s=10 * WAIT_S)
    try:
        device.expect("configured")
        wait_samples(buf, 10)
        device.send("silence 3", "silent")  # (a stall of this machine may count one before)
        before = drv.stats.silences
        # The driver notices (0.3 s without a sample); a frame captured during
        # the silence lies beyond the newest sample: "no attitude".
        assert drv.counters.wait_for(lambda s: s.silences > before, WAIT_S)
        assert buf.rotation_at(time.monotonic()) is None
        device.expect("configured")  # the driver re-sent the start-up commands
        device.expect("talking")
        wait_samples(buf, 10)
        assert wait_fresh_attitude(buf)
        assert drv.stats.disconnects == 0 and drv.alive
    finally:
        assert drv.stop(10)


def test_driver_reopens_a_replugged_device(device) -> None:
    drv, buf, readings = start_driver(device)
    try:
        device.expect("configured")
        wait_samples(buf, 10)
        first_tty = os.readlink(device.link)
        device.send("unplug", "unplugged")
        assert drv.counters.wait_for(lambda s: s.disconnects == 1, WAIT_S)
        old_device = len(readings)  # the port is closed: nothing more from it
        # Absent: the driver keeps trying (the symlink is gone, as udev removes it).
        # Four failed opens take >= 0.75 s of backoff (0.05 + 0.1 + 0.2 + 0.4):
        # a frame captured meanwhile has "no attitude".
        assert drv.counters.wait_for(lambda s: s.open_failures >= 4, WAIT_S)
        assert buf.rotation_at(time.monotonic()) is None
        before = buf.stats.pushed
        device.send("replug", "plugged")
        device.expect("configured")  # settings are volatile: sent again on reopen
        wait_samples(buf, 20)
        s = drv.stats
        assert s.opens == 2 and s.disconnects == 1 and drv.alive
        assert buf.stats.pushed > before
        assert s.parser.checksum_errors == 0 and s.parser.garbage_lines == 0
        assert s.parser.partial_lines <= 1  # at most the sentence the unplug cut
        assert readings[old_device].seq == 0  # the new device counts from 0 again
        new_seqs = [r.seq for r in readings[old_device:]]
        assert new_seqs == list(range(len(new_seqs)))  # every sample, in order
        assert os.path.islink(device.link) and first_tty.startswith("/dev/pts/")
        # A second unplug/replug round works the same.
        device.send("unplug", "unplugged")
        assert drv.counters.wait_for(lambda s: s.disconnects == 2, WAIT_S)
        device.send("replug", "plugged")
        wait_samples(buf, 10)
        assert drv.stats.opens == 3
    finally:
        assert drv.stop(10)  # the pending read is cancelled (a stop time is measured, not asserted)
    print(f"driver stop time {drv.last_stop_s * 1e3:.1f} ms")


def test_driver_stops_while_the_device_is_absent(tmp_path: Path) -> None:
    """stop() cuts the reconnect backoff short: after the first failed open
    the driver would wait 10 min for the next try."""
    buf = AttitudeBuffer()
    drv = MyAhrsDriver(str(tmp_path / "nothing"), buf.push, reconnect_min_s=600.0,
                       reconnect_max_s=600.0)
    drv.start()
    assert drv.counters.wait_for(lambda s: s.open_failures >= 1, WAIT_S)
    assert drv.stop(WAIT_S)  # False (still alive) if it had to sleep the backoff out
    assert drv.stats.open_failures == 1 and buf.stats.pushed == 0
