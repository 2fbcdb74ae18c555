"""A simulated myAHRS+ behind a pseudo-terminal, run as its own process.

    python tests/peers/myahrs_device.py --link DIR/myahrs

It creates a pty pair, exposes the terminal side through a stable symlink
(as a udev rule does for the real device) and speaks the real ASCII protocol
on the other side: it answers `@cmd,args*XX` commands with `~cmd,OK,...*XX`
(`~cmd,ERROR*XX` on a bad checksum) and, once set to `@mode,AC` and
`@asc_out,QUATIMU`, streams `$QUATIMU,...*XX` at 100/divider Hz. Settings are
volatile, as on the device: a replug starts unconfigured and silent, and
counts its samples from 0 again. While the terminal side is not read and
MAX_QUEUED_LINES wait, no sample is made (its seq is not used up), so the
samples a test sees skip only the sequence numbers it broke on purpose.

The quaternion of sample `seq` is a rotation about z by seq * 0.01 rad,
scalar last, so a test can check every parsed value.

Control lines on stdin (one reply line on stdout each, flushed):
  badsum N     the next N sentences carry a wrong checksum  -> "injected badsum N"
  partial N    N sentences cut off before their end          -> "injected partial N"
  garbage N    N lines of noise without a start character    -> "injected garbage N"
  silence S    no output for S seconds (commands answered)   -> "silent S" ... "talking"
  noise S      S seconds of noise lines instead of sentences -> "noise S" ... "clean"
  nan S        S seconds of sentences with NaN values        -> "nan S" ... "clean"
  frozen S     S seconds repeating one sample's values       -> "frozen S" ... "clean"
  unplug       close the pty and remove the symlink          -> "unplugged"
  replug       a new pty behind the same symlink             -> "plugged /dev/pts/N"
  quit
Unprompted: "plugged /dev/pts/N" at start, "configured divider=N" on every
`@divider` command that finds mode AC and output QUATIMU set (the driver
sends the divider last, so once per start-up sequence).
"""

from __future__ import annotations

import argparse
import math
import os
import select
import sys
import time
import tty
from functools import reduce

BASE_RATE_HZ = 100.0
MAX_QUEUED_LINES = 64  # output kept while nobody reads; whole lines only


def checksum(body: bytes) -> bytes:
    return f"{reduce(lambda a, c: a ^ c, body, 0):02X}".encode()


def frame(body: str) -> bytes:
    b = body.encode()
    return b + b"*" + checksum(b) + b"\r\n"


def say(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


class Device:
    def __init__(self, link: str) -> None:
        self.link = link
        self.master: int | None = None
        self.slave: int | None = None
        self.rx = bytearray()
        self.out: list[bytes] = []  # lines waiting for the pty; out[0] may be partly sent
        self.sent_of_first = 0
        self.reset_settings()
        self.seq = 0
        self.badsum = 0
        self.partial = 0
        self.silent_until = 0.0
        self.spoilt: tuple[str, float] | None = None  # (noise | nan | frozen, until)
        self.frozen_line: bytes | None = None
        self.next_due = time.monotonic()

    def reset_settings(self) -> None:
        self.mode = ""
        self.asc_out = ""
        self.divider = 1
        self.configured = False

    # -- plugging

    def plug(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no line editing: a serial line
        os.set_blocking(self.master, False)
        name = os.ttyname(self.slave)
        tmp = self.link + ".tmp"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(name, tmp)
        os.replace(tmp, self.link)  # atomic re-point, as udev does
        self.reset_settings()
        self.seq = 0  # a device powered up again counts from 0
        self.rx.clear()
        self.out.clear()
        self.sent_of_first = 0
        say(f"plugged {name}")

    def unplug(self) -> None:
        if os.path.lexists(self.link):
            os.unlink(self.link)
        for fd in (self.master, self.slave):
            if fd is not None:
                os.close(fd)
        self.master = self.slave = None
        say("unplugged")

    # -- protocol

    def handle_rx(self) -> None:
        while True:
            end = self.rx.find(b"\n")
            if end < 0:
                return
            line = bytes(self.rx[:end]).strip()
            del self.rx[: end + 1]
            if line.startswith(b"@"):
                self.command(line)

    def command(self, line: bytes) -> None:
        body, _, sent = line.rpartition(b"*")
        name = body[1:].split(b",")[0].decode(errors="replace")
        if checksum(body) != sent:
            self.queue(frame(f"~{name},ERROR"))
            return
        args = body[1:].decode().split(",")[1:]
        if name == "mode" and args:
            self.mode = args[0]
            reply = f"~mode,OK,mode={self.mode}"
        elif name == "asc_out" and args:
            self.asc_out = args[0]
            reply = f"~asc_out,OK,fmt={self.asc_out}"
        elif name == "divider" and args and args[0].isdigit() and int(args[0]) >= 1:
            self.divider = int(args[0])
            reply = f"~divider,OK,divider={self.divider},max rate=100"
        else:
            reply = f"~{name},ERROR"
        self.queue(frame(reply))
        self.configured = self.mode == "AC" and self.asc_out == "QUATIMU"
        if self.configured and name == "divider":  # the driver sends the divider last
            say(f"configured divider={self.divider}")

    def sample_line(self) -> bytes:
        kind = self.spoilt[0] if self.spoilt else ""
        if kind == "noise":
            return b"\x07noise\xff%d\r\n" % self.seq
        if kind == "frozen" and self.frozen_line is not None:
            return self.frozen_line
        line = self._sample_line()
        if kind == "nan":
            body = line[:line.index(b"*")].decode().split(",")
            body[2:6] = ["nan"] * 4
            line = frame(",".join(body))
        self.frozen_line = line
        return line

    def _sample_line(self) -> bytes:
        seq = self.seq
        self.seq += 1
        half = 0.5 * 0.01 * seq
        x, y, z, w = 0.0, 0.0, math.sin(half), math.cos(half)
        body = (f"$QUATIMU,{seq},{x:.6f},{y:.6f},{z:.6f},{w:.6f},"
                f"0.0010,-0.0020,-1.0000,0.1000,-0.2000,0.3000,120.0,-80.0,130.0,35.5")
        line = frame(body)
        if self.badsum:
            self.badsum -= 1
            good = line[-4:-2]
            bad = b"00" if good != b"00" else b"FF"
            line = line[:-4] + bad + b"\r\n"
        elif self.partial:
            self.partial -= 1
            line = line[: len(line) // 2]  # cut off: the next sentence starts right after
        return line

    # -- output

    def queue(self, line: bytes) -> None:
        if len(self.out) < MAX_QUEUED_LINES:
            self.out.append(line)

    def flush(self) -> None:
        while self.out and self.master is not None:
            first = self.out[0]
            try:
                n = os.write(self.master, first[self.sent_of_first:])
            except BlockingIOError:
                return
            self.sent_of_first += n
            if self.sent_of_first < len(first):
                return
            self.out.pop(0)
            self.sent_of_first = 0

    # -- main loop

    def control(self, line: str) -> bool:
        parts = line.split()
        if not parts:
            return True
        cmd, arg = parts[0], (parts[1] if len(parts) > 1 else "0")
        if cmd == "badsum":
            self.badsum += int(arg)
            say(f"injected badsum {arg}")
        elif cmd == "partial":
            self.partial += int(arg)
            say(f"injected partial {arg}")
        elif cmd == "garbage":
            for i in range(int(arg)):
                self.queue(b"\x07noise\xff%d\r\n" % i)
            say(f"injected garbage {arg}")
        elif cmd in ("noise", "nan", "frozen"):
            self.spoilt = (cmd, time.monotonic() + float(arg))
            say(f"{cmd} {arg}")
        elif cmd == "silence":
            self.silent_until = time.monotonic() + float(arg)
            say(f"silent {arg}")
        elif cmd == "unplug":
            self.unplug()
        elif cmd == "replug":
            self.plug()
        elif cmd == "quit":
            return False
        return True

    def run(self) -> None:
        self.plug()
        was_silent = False
        while True:
            now = time.monotonic()
            silent = now < self.silent_until
            if was_silent and not silent:
                say("talking")
            was_silent = silent
            if self.spoilt is not None and now >= self.spoilt[1]:
                self.spoilt = None
                say("clean")
            streaming = self.master is not None and self.configured and not silent
            period = self.divider / BASE_RATE_HZ
            if streaming and now >= self.next_due:
                if len(self.out) < MAX_QUEUED_LINES:  # else held back, not lost
                    self.queue(self.sample_line())
                self.next_due = max(self.next_due + period, now - period)
            if not streaming:
                self.next_due = now
            self.flush()
            fds = [sys.stdin.fileno()] + ([self.master] if self.master is not None else [])
            wfds = [self.master] if self.out and self.master is not None else []
            timeout = max(0.0, min(self.next_due - time.monotonic(), 0.05))
            r, _w, _x = select.select(fds, wfds, [], timeout)
            if sys.stdin.fileno() in r:
                line = sys.stdin.readline()
                if not line or not self.control(line):
                    break
            if self.master is not None and self.master in r:
                try:
                    self.rx += os.read(self.master, 4096)
                    self.handle_rx()
                except OSError:  # EIO: no terminal side open right now
                    pass
        if self.master is not None:
            self.unplug()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--link", required=True, help="stable symlink to the terminal side")
    Device(ap.parse_args().link).run()


if __name__ == "__main__":
    main()
