"""systemd's notify protocol with the standard library (sd_notify(3)).

`Type=notify` services tell systemd READY=1 once up, WATCHDOG=1 at least
every `WatchdogSec`, STATUS=<one line> for `systemctl status`, and
STOPPING=1 on the way down. systemd passes the socket in NOTIFY_SOCKET (a
path, or an abstract socket when it starts with '@') and the watchdog period
in WATCHDOG_USEC (for the process WATCHDOG_PID, when set). Outside systemd
there is no socket and every call does nothing.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from collections.abc import Callable, Mapping

log = logging.getLogger(__name__)


class Notifier:
    """Datagrams to NOTIFY_SOCKET; `watchdog()` rate-limits itself to half
    the watchdog period (sd_watchdog_enabled(3) recommends pinging at that)."""

    def __init__(self, env: Mapping[str, str] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        env = os.environ if env is None else env
        self._clock = clock
        self.address = _address(env.get("NOTIFY_SOCKET", ""))
        self.watchdog_period_s = _watchdog_period_s(env)
        self._sock: socket.socket | None = None
        self._next_ping = 0.0
        self.sent: dict[str, int] = {}  # message kind -> count (READY, WATCHDOG, ...)
        if self.address is not None:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def ready(self, status: str = "") -> None:
        self._send("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def status(self, text: str) -> None:
        self._send(f"STATUS={text}")

    def stopping(self) -> None:
        self._send("STOPPING=1")

    def watchdog(self) -> None:
        """Ping if half the watchdog period has passed since the last ping."""
        if self.watchdog_period_s is None:
            return
        now = self._clock()
        if now >= self._next_ping:
            self._next_ping = now + self.watchdog_period_s / 2.0
            self._send("WATCHDOG=1")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _send(self, message: str) -> None:
        if self._sock is None or self.address is None:
            return
        try:
            self._sock.sendto(message.encode(), self.address)
        except OSError as e:  # systemd restarting, socket gone: never fatal
            log.debug("sd_notify %r failed: %s", message, e)
            return
        kind = message.split("=", 1)[0]
        self.sent[kind] = self.sent.get(kind, 0) + 1


def _address(value: str) -> str | bytes | None:
    if not value:
        return None
    if value.startswith("@"):  # abstract namespace: a leading NUL byte
        return b"\0" + value[1:].encode()
    if value.startswith("/"):
        return value
    log.warning("NOTIFY_SOCKET=%r is neither a path nor an abstract socket; ignored", value)
    return None


def _watchdog_period_s(env: Mapping[str, str]) -> float | None:
    usec = env.get("WATCHDOG_USEC", "")
    pid = env.get("WATCHDOG_PID", "")
    if not usec:
        return None
    if pid and pid != str(os.getpid()):
        return None  # meant for another process (our parent, say)
    try:
        period = int(usec) * 1e-6
    except ValueError:
        log.warning("WATCHDOG_USEC=%r is not an integer; watchdog pings off", usec)
        return None
    return period if period > 0 else None
