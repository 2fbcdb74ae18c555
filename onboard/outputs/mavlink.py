"""The MAVLink vision-position feed to the flight controller.

Per tracked frame one ODOMETRY (or, selectable, VISION_POSITION_ESTIMATE +
VISION_SPEED_ESTIMATE), a HEARTBEAT at 1 Hz from component 197 telling how
tracking goes, a STATUSTEXT on every change of that, TIMESYNC answers and,
optionally, the EKF origin once at start. Facts behind every field:
../shared/docs/reference-flight-stack.md; the autopilot settings:
docs/autopilot.md. What the samples hold and when: onboard.outputs.mavlink_feed.

Threads. `publish()` only appends the result to a bounded queue (the oldest
dropped when full) and wakes the sender thread, which owns the link: it
converts, sends, answers TIMESYNC (reading its own link every 2 ms) and asks
its own (mavlink_timesync), keeps the heartbeat and reopens a failed link
every `reconnect_s`: the loop never waits on a socket or a serial port.
Errors are counted and logged once per spell. A link shared with the
autopilot attitude source (drivers.fc_link.FcLink) is passed as `link`.

pymavlink is imported only inside `load_mavutil()` (mavutil_loader.py), so
importing onboard.outputs.mavlink has no side effect.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from onboard import NislamError
from onboard.core.messages import HealthReport, KeyframeCloud, TrackResult
from onboard.outputs.mavlink_feed import (
    HEALTH_STATE,
    MAV_AUTOPILOT_INVALID,
    MAV_TYPE_ONBOARD_CONTROLLER,
    SEVERITY,
    STATUSTEXT_LEN,
    FeedEvent,
    FeedState,
    VisionFeed,
    VisionSample,
    diag_cov21,
    euler_rpy,
    odometry_args,
)
from onboard.outputs.mavlink_origin import OriginHandshake, ResetCounterStore, state_directory
from onboard.outputs.mavlink_signing import enable_signing, load_signing_key
from onboard.outputs.mavlink_stats import MavlinkStats, SharedLink
from onboard.outputs.mavlink_timesync import PACKET_BYTES, TimesyncClock
from onboard.outputs.mavutil_loader import load_mavutil
from onboard.outputs.settings import MavlinkConfig
from onboard.outputs.wake import Wake

log = logging.getLogger(__name__)

RX_POLL_S = 0.002  # how often our own link is read: TIMESYNC answers within ~2 ms
ANSWER_WAIT_S = 0.02  # the sender reads at once for an answer to our TIMESYNC this long


# --------------------------------------------------------------------------- sender


class MavlinkOutput:
    """The feed on its own thread; see the module docstring. An `Output`.

    With `link` (a `SharedLink`) it sends and listens on that connection,
    which opens, reconnects and logs by itself; without, it opens
    `cfg.connect` and looks after it."""

    def __init__(
        self, cfg: MavlinkConfig, clock_ns: Callable[[], int] = time.monotonic_ns,
        link: SharedLink | None = None, host_time_s: Callable[[float], float] | None = None,
    ) -> None:
        self.cfg = cfg
        self._mavutil = load_mavutil()
        self._mav = self._mavutil.mavlink
        # reset_counter goes on from the last one any earlier process sent
        # (mavlink_origin); `host_time_s` maps replayed stamps onto our clock.
        self.counter_store = ResetCounterStore(state_directory(cfg.state_dir))
        self.feed = VisionFeed.from_config(cfg, self.counter_store.start_counter(), host_time_s)
        self._clock_ns = clock_ns
        self._queue: deque[TrackResult] = deque(maxlen=cfg.queue_frames)
        self._lock = threading.Lock()
        self._stats = MavlinkStats()
        self._stop = threading.Event()
        self._wakeup = Wake()  # never makes the loop wait (onboard/outputs/wake.py)
        self._conn: Any = None
        self._link_dead: str | None = None
        self._next_open = 0.0
        self._spell: tuple[float, int] | None = None  # (start, errors) of a failure spell
        self._next_heartbeat = 0.0
        self._last_result_at: float | None = None
        self._origin = OriginHandshake(cfg)
        self._shared = link
        # MAVLink 2 signing (mavlink_signing.py) on a link we open ourselves.
        self._signing_key = load_signing_key(cfg.signing_key_file) if cfg.signing_key_file else None
        if self._signing_key is not None and link is not None:
            raise NislamError("[mavlink] signing_key_file: signing is not available on a link "
                              "shared with the autopilot attitude source (ahrs.source = "
                              "\"autopilot\") yet")
        self._rx: deque[Any] = deque(maxlen=64)  # messages a shared link handed over
        self._health: FeedState | None = None  # the loop's health, when it reports one
        self._health_texts: deque[tuple[int, str, FeedState]] = deque(maxlen=8)
        self._remove_listener: Callable[[], None] | None = None
        if link is not None:
            self._remove_listener = link.add_listener(
                self._on_shared_message, ("TIMESYNC", "GPS_GLOBAL_ORIGIN"))
        # Our TIMESYNC requests; hooks (onboard.app.latency.attach_timing).
        self.timesync = TimesyncClock()
        self.on_written: Callable[[int, float], None] | None = None
        self.on_stage: Callable[[str, float], None] | None = None
        self._send_started = self._pose_written = 0.0  # time.monotonic() [s]
        serial = not cfg.connect.startswith(("udp", "tcp"))  # a pose's transmit time:
        self._transmit_s = PACKET_BYTES[cfg.message] * 10 / cfg.baud if serial else 0.0
        self._thread = threading.Thread(target=self._run, name="mavlink-out", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------- Output API
    def publish(self, result: TrackResult) -> None:
        # deque.append is atomic and drops the oldest when full; the loop is
        # the only producer, so the drop count needs no lock either.
        if len(self._queue) == self._queue.maxlen:
            self._stats.dropped += 1
        self._queue.append(result)
        self._wakeup.set()

    def publish_keyframe(self, cloud: KeyframeCloud) -> None:
        pass  # the flight controller has no use for the map

    def publish_health(self, report: HealthReport) -> None:
        state = HEALTH_STATE[report.state]
        if state is self._health and not report.changed:
            return
        self._health = state  # one attribute store: atomic; the sender reads it
        if report.changed:
            self._health_texts.append(
                (SEVERITY[state], f"{report.state.value}: {report.reason}", state)
            )
        self._wake()

    def close(self, timeout_s: float = 2.0) -> None:
        """Send what is queued, then stop; the link closes with the thread."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._wakeup.set_now()
        self._thread.join(timeout_s)
        if self._remove_listener is not None:
            self._remove_listener()
        if self._thread.is_alive():
            log.warning("MAVLink sender did not stop within %.1f s (link %s busy)",
                        timeout_s, self.cfg.connect)

    def stats(self) -> dict[str, Any]:
        with self._lock:
            s = self._stats
            out = {k: getattr(s, k) for k in s.__dataclass_fields__}
            out["sent_by_type"] = dict(s.sent_by_type)
        out["timesync"] = self.timesync_estimate()
        out["state"] = self.feed.state.name
        out["system_status"] = self._system_status.name
        out["reset_counter"] = self.feed.reset_counter
        out["shared_link"] = self._shared is not None  # `received` then counts TIMESYNC only
        return out

    def timesync_estimate(self) -> dict[str, Any] | None:
        """Our TIMESYNC answers' clock offset and round trip [ms], or None."""
        est = self.timesync.estimate()
        return None if est is None else est.as_dict()

    def one_way_s(self) -> float | None:
        """A pose's time on the link (half the least round trip + transmit), or None."""
        half_rtt = self.timesync.one_way_s()
        return None if half_rtt is None else half_rtt + self._transmit_s

    def __enter__(self) -> MavlinkOutput:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------- the thread
    def _wake(self) -> None:
        self._wakeup.set()  # the loop's calls: deferred to its frame's end in the service

    def wakeups(self) -> tuple[Wake, ...]:
        return (self._wakeup,)

    def _on_shared_message(self, msg: Any, t_ns: int) -> None:
        self._rx.append((msg, t_ns))  # on the link's reader thread: hand over, wake, return
        self._wakeup.set_now()

    @property
    def _link_open(self) -> bool:
        return self._shared is not None or self._conn is not None

    def _run(self) -> None:
        if self._shared is not None:
            self._heartbeat()  # BOOT until the first result
        try:
            while True:
                stopping = self._stop.is_set()
                self._step(stopping)
                if stopping:
                    break
        except Exception:  # a bug: log it, the loop keeps running without us
            log.exception("MAVLink sender stopped")
        finally:
            self._close_link()

    def _step(self, stopping: bool) -> None:
        now = time.monotonic()
        if not self._link_open and now >= self._next_open:
            self._open_link(now)
        if not stopping:
            self._wait(now)
        if self._link_open:
            self._receive()
        while self._health_texts:
            severity, text, state = self._health_texts.popleft()
            self._statustext(severity, text)
            # Each change's own state at once, even when the next change came
            # before this thread woke (a first frame that tracks at once would
            # otherwise never show STANDBY).
            self._heartbeat(state)
        while self._queue:
            result = self._queue.popleft()
            with self._lock:
                self._stats.results += 1
            self._last_result_at = time.monotonic()
            self._handle(self.feed.update(result), result.trusted and result.p_W_m is not None)
        now = time.monotonic()
        last = self._last_result_at
        if last is not None and now - last > self.cfg.stale_s:
            event = self.feed.stale(now - last)
            if event is not None:
                self._handle(event)
        if now >= self._next_heartbeat:
            self._heartbeat()
        if self._link_open:
            ts1 = self.timesync.due(self._clock_ns())
            if ts1 is not None and self._send("timesync", 0, ts1):
                with self._lock:
                    self._stats.timesync_requests += 1
                if self.timesync.answers:  # a peer that never answers costs no wait
                    self._await_answer(ts1)
        if self._link_open and self._origin.due(now):
            for name, args in self._origin.messages(now, self._clock_ns() // 1000):
                self._send(name, *args)

    def _wait(self, now: float) -> None:
        deadlines = [self._next_heartbeat]
        if not self._link_open:
            deadlines.append(self._next_open)
        elif not self._origin.done:
            deadlines.append(self._origin.next_s)
        next_ts = self.timesync.next_due_ns()
        if self._link_open and next_ts is not None:
            deadlines.append(now + (next_ts - self._clock_ns()) / 1e9)
        watching = self.feed.state not in (FeedState.BOOT, FeedState.LOST)
        if watching and self._last_result_at is not None:
            deadlines.append(self._last_result_at + self.cfg.stale_s + 1e-3)
        timeout = min(0.5, max(0.0, min(deadlines) - now))
        if self._conn is not None:
            timeout = min(timeout, RX_POLL_S)  # our own link: look for TIMESYNC requests
        idle = not (self._queue or self._rx or self._health_texts)
        if idle and not self._stop.is_set():
            self._wakeup.wait(timeout)  # a signal set before it returns at once

    # ------------------------------------------------------------- link
    def _open_link(self, now: float) -> None:
        try:
            conn = self._mavutil.mavlink_connection(
                self.cfg.connect, baud=self.cfg.baud, source_system=self.cfg.system_id,
                source_component=self.cfg.component_id, autoreconnect=False, retries=0,
            )
        except Exception as e:  # noqa: BLE001 - OSError, SerialException, socket errors
            self._failed(f"cannot open: {e}", now)
            return
        # pymavlink reports a closed TCP peer with print() and carries on
        # without autoreconnect; route that into our reopen logic instead.
        if hasattr(conn, "handle_eof"):
            conn.handle_eof = lambda: self._mark_dead("closed by the peer")
            conn.handle_disconnect = lambda: self._mark_dead("connection reset")
        if self._signing_key is not None:
            enable_signing(conn, self._signing_key, self.cfg.signing_link_id)
        port = getattr(conn, "port", None)
        if port is not None and hasattr(port, "write_timeout"):
            port.write_timeout = 0.05  # a serial port that stops draining fails, not blocks
        self._conn = conn
        self._link_dead = None
        with self._lock:
            self._stats.link_up = True
            self._stats.link_opens += 1
        if self._spell is not None:
            start, errors = self._spell
            log.warning("MAVLink link %s open again after %.1f s (%d errors)",
                        self.cfg.connect, now - start, errors)
            self._spell = None
        else:
            log.info("MAVLink link %s open", self.cfg.connect)
        self._heartbeat()  # announce ourselves (BOOT until the first result) at once

    def _mark_dead(self, reason: str) -> None:
        self._link_dead = self._link_dead or reason

    def _failed(self, reason: str, now: float) -> None:
        """Count an error; log the first of a spell; reopen later."""
        with self._lock:
            self._stats.link_errors += 1
            self._stats.link_up = False
        if self._spell is None:
            self._spell = (now, 1)
            log.warning("MAVLink link %s: %s; retrying every %.1f s",
                        self.cfg.connect, reason, self.cfg.reconnect_s)
        else:
            self._spell = (self._spell[0], self._spell[1] + 1)
        self._close_link()
        self._next_open = now + self.cfg.reconnect_s

    def _close_link(self) -> None:
        conn, self._conn = self._conn, None
        if conn is not None:
            try:
                conn.close()
            except Exception:  # noqa: BLE001 - closing a broken port may fail too
                pass

    def _send(self, name: str, *args: Any) -> bool:
        """Call `mav.<name>_send(*args)`; False (and the link reopens) on failure."""
        if self._shared is not None:
            ok = self._shared.send(lambda mav: self._call(mav, name, args))
            if ok:
                with self._lock:
                    counts = self._stats.sent_by_type
                    counts[name] = counts.get(name, 0) + 1
            return ok
        conn = self._conn
        if conn is None:
            return False
        try:
            self._call(conn.mav, name, args)
        except Exception as e:  # noqa: BLE001 - socket, serial and struct errors alike
            self._failed(f"send failed: {e}", time.monotonic())
            return False
        dead = self._link_dead or ("port dead" if getattr(conn, "portdead", False) else None)
        if dead is not None:
            self._failed(dead, time.monotonic())
            return False
        with self._lock:
            counts = self._stats.sent_by_type
            counts[name] = counts.get(name, 0) + 1
        return True

    def _call(self, mav: Any, name: str, args: tuple) -> None:
        # When the send began: after it this thread may wait 30 ms for the GIL.
        self._send_started = time.monotonic()
        getattr(mav, name + "_send")(*args)

    def _receive(self) -> None:
        """Answer TIMESYNC requests; note the origin's confirmation."""
        if self._shared is not None:
            while self._rx:
                self._on_message(*self._rx.popleft())
            return
        for _ in range(100):
            conn = self._conn
            if conn is None:
                return
            try:
                msg = conn.recv_msg()
            except Exception as e:  # noqa: BLE001
                self._failed(f"receive failed: {e}", time.monotonic())
                return
            if self._link_dead is not None:
                self._failed(self._link_dead, time.monotonic())
                return
            if msg is None:
                return
            self._on_message(msg, self._clock_ns())

    def _await_answer(self, ts1: int) -> None:
        """Read our link at once until `ts1` is answered (polling adds offset error)."""
        deadline = time.monotonic() + ANSWER_WAIT_S
        while self._conn is not None and self.timesync.pending(ts1):
            left = deadline - time.monotonic()
            if left <= 0 or not self._conn.select(left):
                return
            self._receive()

    def _on_message(self, msg: Any, t_rx_ns: int) -> None:
        kind = msg.get_type()
        rejected = kind == "BAD_DATA" and "signature" in str(getattr(msg, "reason", ""))
        with self._lock:
            self._stats.received += 1
            self._stats.signature_rejects += int(rejected)
        if rejected:
            return
        if kind == "TIMESYNC" and msg.tc1 == 0:
            if self._send("timesync", self._clock_ns(), msg.ts1):
                with self._lock:
                    self._stats.timesync_replies += 1
        elif kind == "TIMESYNC":  # an answer: to one of our requests?
            if self.timesync.on_answer(msg.tc1, msg.ts1, t_rx_ns):
                with self._lock:
                    self._stats.timesync_answers += 1
        elif kind == "GPS_GLOBAL_ORIGIN":
            self._origin.on_confirmed()

    # ------------------------------------------------------------- messages
    def _handle(self, event: FeedEvent, trusted: bool = True) -> None:
        for severity, text in self._event_texts(event):
            self._statustext(severity, text)
        if event.changed:
            self._heartbeat()
        if event.sample is None:
            return
        t0 = time.perf_counter()
        sent = (self._send_odometry(event.sample) if self.cfg.message == "odometry"
                else self._send_vision(event.sample))
        t_written = self._pose_written
        with self._lock:
            if sent:
                self._stats.poses_sent += 1
                self._stats.untrusted_sent += int(not trusted)
            else:
                self._stats.not_sent += 1
        if self.on_stage is not None:
            self.on_stage("mavlink_encode_send", (time.perf_counter() - t0) * 1e3)
        if sent and self.on_written is not None:
            self.on_written(event.sample.time_usec, t_written)
        if sent:
            self.counter_store.save(event.sample.reset_counter)

    def _event_texts(self, event: FeedEvent) -> tuple[tuple[int, str], ...]:
        """One STATUSTEXT per transition: when the loop reports its health
        (publish_health, which says every change itself), the feed's own
        state changes stay silent; its resets are always told."""
        if self._health is not None:
            return event.notices
        return event.notices + event.texts

    def _send_odometry(self, s: VisionSample) -> bool:
        ok = self._send("odometry", *odometry_args(s))
        self._pose_written = self._send_started
        return ok

    def _send_vision(self, s: VisionSample) -> bool:
        ok = self._send(
            "vision_position_estimate", s.time_usec, *s.p_L_m.tolist(),
            *euler_rpy(s.R_L_B).tolist(), diag_cov21(s.pose_var), s.reset_counter,
        )
        self._pose_written = self._send_started
        if ok and np.all(np.isfinite(s.v_L_m_s)):
            cov9 = [0.0] * 9
            cov9[0], cov9[4], cov9[8] = (float(v) for v in s.v_var_L)
            ok = self._send("vision_speed_estimate", s.time_usec, *s.v_L_m_s.tolist(), cov9,
                            s.reset_counter)
        return ok

    @property
    def _system_status(self) -> FeedState:
        return self._health if self._health is not None else self.feed.state

    def _heartbeat(self, state: FeedState | None = None) -> None:
        self._next_heartbeat = time.monotonic() + self.cfg.heartbeat_period_s
        state = self._system_status if state is None else state
        if self._send("heartbeat", MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0,
                      state.mav_state):
            with self._lock:
                self._stats.heartbeats += 1

    def _statustext(self, severity: int, text: str) -> None:
        data = ("NISLAM: " + text).encode("ascii", "replace")[:STATUSTEXT_LEN]
        log.info("status: %s", data.decode("ascii"))
        if self._send("statustext", severity, data):
            with self._lock:
                self._stats.statustexts += 1
