"""The MAVLink link to one flight controller, shared by everything that talks to it.

One `FcLink` per flight controller: the autopilot attitude source
(drivers/autopilot_attitude.py) listens on it and the MAVLink output sends
on it, so the autopilot sees one companion on one serial port or UDP socket.

- Receive hook: `add_listener(callback, types)`; the reader thread calls
  `callback(msg, t_arrival_ns)` for every message of those types, stamped on
  the monotonic clock right after the read. Callbacks run on the reader
  thread and must be quick (parse, push into a buffer).
- Send hook: `send(build)` calls `build(mav)` with the connection's pymavlink
  `MAVLink` object under the write lock, e.g.
  `link.send(lambda mav: mav.heartbeat_send(...))`; False when the link is
  down. The lock covers writes only: the reader thread never holds it while
  it waits for data.
- A link that fails (serial device unplugged) is closed and reopened with
  backoff; `generation` counts successful opens so users can redo their
  start-up requests on a fresh connection.

- `device_state` (drivers/device_state.py): no device (cannot open, lost),
  open (nothing heard yet), streaming, silent (nothing heard for `silence_s`:
  over UDP, nobody may be there), bad data (only bytes pymavlink rejects).

pymavlink is imported lazily by `import_mavutil()`; see there for MAVLINK20.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from types import ModuleType
from typing import Any

from drivers.device_state import DeviceState, State
from onboard.core.sources import Backoff, Counters, DriverThread

log = logging.getLogger(__name__)

Listener = Callable[[Any, int], object]


def import_mavutil() -> ModuleType:
    """`pymavlink.mavutil` with the MAVLink 2 dialect loaded.

    pymavlink picks its dialect module when `mavutil` is first imported, from
    the MAVLINK20 environment variable: without it the v1 dialect loads, which
    lacks ODOMETRY and MAVLink-2 extension fields (VISION_POSITION_ESTIMATE's
    covariance and reset_counter). So MAVLINK20 must be set BEFORE that first
    import. It is set here, inside the function that imports pymavlink, not at
    module level: importing this module has no side effects, and whichever
    part of the program first needs MAVLink sets it just in time. If pymavlink
    was already imported without it, the dialect is reloaded as MAVLink 2.
    """
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    if getattr(mavutil.mavlink, "WIRE_PROTOCOL_VERSION", "1.0") != "2.0":
        mavutil.set_dialect(mavutil.current_dialect)
    return mavutil


@dataclass(frozen=True)
class FcLinkStats:
    opens: int = 0
    open_failures: int = 0
    disconnects: int = 0
    received: int = 0  # messages parsed
    bad_data: int = 0  # bytes pymavlink could not parse (BAD_DATA)
    sent: int = 0
    send_skipped: int = 0  # send() while the link was down
    send_failures: int = 0
    callback_errors: int = 0


class FcLink(DriverThread):
    """A pymavlink connection (`udpout:HOST:PORT`, `udpin:...`, `tcp:...`,
    `/dev/ttyAMA0` or `/dev/ttyAMA0,921600`) with a reader thread."""

    def __init__(
        self,
        connect: str,
        *,
        baud: int = 921600,
        source_system: int = 1,
        source_component: int = 197,
        reconnect_min_s: float = 0.2,
        reconnect_max_s: float = 2.0,
        poll_s: float = 0.1,
        connection_factory: Callable[..., Any] | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        silence_s: float = 3.0,  # three missed 1 Hz HEARTBEATs
    ) -> None:
        super().__init__(f"fc_link:{connect}")
        self.device_state = DeviceState("autopilot link", connect)
        self.silence_ns = int(silence_s * 1e9)
        self.connect = connect
        self.baud = baud
        self.source_system = source_system
        self.source_component = source_component
        self.backoff = Backoff(reconnect_min_s, reconnect_max_s)
        self.poll_s = poll_s
        self.connection_factory = connection_factory
        self.clock_ns = clock_ns
        self.counters: Counters[FcLinkStats] = Counters(FcLinkStats())
        self.connected = threading.Event()
        self.generation = 0  # successful opens so far
        self._conn: Any = None
        self._write_lock = threading.Lock()
        self._listeners_lock = threading.Lock()
        self._listeners: list[tuple[frozenset[str] | None, Listener]] = []
        self._mavutil: ModuleType | None = None

    @property
    def stats(self) -> FcLinkStats:
        return self.counters.snapshot()

    @property
    def dialect(self) -> ModuleType:
        """The pymavlink dialect module (message classes, MAV_* constants)."""
        if self._mavutil is None:
            self._mavutil = import_mavutil()
        return self._mavutil.mavlink

    # -- hooks

    def add_listener(self, callback: Listener, types: Iterable[str] | None = None
                     ) -> Callable[[], None]:
        """Call `callback(msg, t_arrival_ns)` for messages of `types` (all when
        None). Returns a function that removes the listener."""
        entry = (frozenset(types) if types is not None else None, callback)
        with self._listeners_lock:
            self._listeners = [*self._listeners, entry]

        def remove() -> None:
            with self._listeners_lock:
                self._listeners = [e for e in self._listeners if e is not entry]

        return remove

    def send(self, build: Callable[[Any], object]) -> bool:
        """Run `build(mav)` under the write lock; False if the link is down or
        the write failed (the reader thread reconnects)."""
        with self._write_lock:
            conn = self._conn
            if conn is None:
                self.counters.bump(send_skipped=1)
                return False
            try:
                build(conn.mav)
            except OSError as e:
                self.counters.bump(send_failures=1)
                log.warning("%s: send failed: %s", self.connect, e)
                return False
        self.counters.bump(sent=1)
        return True

    # -- thread

    def _run(self) -> None:
        try:
            self._run_link()
        finally:
            self.device_state.set(State.CLOSED)

    def _run_link(self) -> None:
        if self._mavutil is None:
            self._mavutil = import_mavutil()
        while not self.stopping:
            conn = self._open()
            if conn is None:
                if self._sleep(self.backoff.next()):
                    break
                continue
            try:
                self._read(conn)
            except OSError as e:  # serial.SerialException is an OSError
                if not self.stopping:
                    log.info("%s: link lost: %s", self.connect, e)
                    self.device_state.set(State.NO_DEVICE, f"link lost: {e}")
                    self.counters.bump(disconnects=1)
            finally:
                self.connected.clear()
                with self._write_lock:
                    self._conn = None
                _close_quietly(conn)
            if not self.stopping and self._sleep(self.backoff.next()):
                break

    def _open(self) -> Any:
        factory = self.connection_factory or self._mavutil.mavlink_connection
        try:
            conn = factory(self.connect, baud=self.baud, source_system=self.source_system,
                           source_component=self.source_component, autoreconnect=False)
        except (OSError, ValueError) as e:
            log.debug("%s: cannot open: %s", self.connect, e)
            self.device_state.set(State.NO_DEVICE, f"cannot open: {e}")
            self.counters.bump(open_failures=1)
            return None
        # pymavlink reports a TCP peer that closed (an autopilot or SITL
        # restarting) with print() and, without autoreconnect, keeps reading
        # the dead socket for ever: make it an error the reader reopens on.
        if hasattr(conn, "handle_eof"):
            conn.handle_eof = _raise_closed
            conn.handle_disconnect = _raise_closed
        with self._write_lock:
            self._conn = conn
        self.generation += 1
        self.connected.set()
        self.device_state.set(State.OPEN)
        self.counters.bump(opens=1)
        log.info("%s: MAVLink link open", self.connect)
        return conn

    def _read(self, conn: Any) -> None:
        last_good_ns = self.clock_ns()
        bad = 0  # BAD_DATA since the last good message
        mav = getattr(conn, "mav", None)
        n_bytes = lambda: getattr(mav, "total_bytes_received", 0)  # noqa: E731
        bytes_at_good = n_bytes()
        while not self.stopping:
            msg = conn.recv_match(blocking=True, timeout=self.poll_s)
            t_ns = self.clock_ns()
            # UNKNOWN_<id>: pymavlink cannot check the CRC of an id it does not
            # know, so junk parses as such: no proof of a live peer.
            if msg is None or msg.get_type() == "BAD_DATA" or \
                    msg.get_type().startswith("UNKNOWN_"):
                if msg is not None:
                    bad += 1
                    self.counters.bump(bad_data=1)
                quiet_s = (t_ns - last_good_ns) * 1e-9
                if quiet_s * 1e9 >= self.silence_ns:
                    junk = n_bytes() - bytes_at_good
                    if bad or junk > 0:
                        self.device_state.set(State.BAD_DATA, (
                            f"{junk} bytes ({bad} rejected messages), no valid message for "
                            f"{quiet_s:.0f} s (wrong baud rate or protocol?)"))
                    else:
                        self.device_state.set(State.SILENT, (
                            f"nothing heard for {quiet_s:.0f} s (is the peer up and "
                            f"sending to us?)"))
                continue
            last_good_ns, bad, bytes_at_good = t_ns, 0, n_bytes()
            self.device_state.set(State.STREAMING)
            self.backoff.reset()
            self.counters.bump(received=1)
            self._dispatch(msg, t_ns)

    def _dispatch(self, msg: Any, t_ns: int) -> None:
        kind = msg.get_type()
        with self._listeners_lock:
            listeners = self._listeners
        for types, callback in listeners:
            if types is not None and kind not in types:
                continue
            try:
                callback(msg, t_ns)
            except Exception:  # noqa: BLE001 - a faulty listener must not take the link down
                self.counters.bump(callback_errors=1)
                log.exception("%s: listener failed on %s", self.connect, kind)


def _raise_closed() -> None:
    raise ConnectionResetError("closed by the peer")


def _close_quietly(conn: Any) -> None:
    try:
        conn.close()
    except OSError:
        log.debug("close failed", exc_info=True)
