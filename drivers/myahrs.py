"""myAHRS+ over serial (USB CDC or UART): transport thread + protocol parser.

Protocol (withrobot/myAHRS_plus user guide; ref. flight-stack doc §9):
commands `@cmd,args*XX\\r\\n`, replies `~cmd,OK|ERROR,...*XX\\r\\n`, data
`$...*XX\\r\\n`, where XX is the XOR of every byte from the start character
through the body, two upper-case hex digits (`@version*3A`). Settings are
volatile, so every (re)connect sends `@mode,AC` (ASCII, continuous),
`@asc_out,QUATIMU` and `@divider,N` (100/N Hz). `$QUATIMU,seq,x,y,z,w,ax,ay,
az,gx,gy,gz,mx,my,mz,temp` carries the quaternion SCALAR LAST, accel in g,
gyro in deg/s.

`MyAhrsParser` is the pure protocol part (bytes in, sentences out, counters);
`MyAhrsDriver` the transport: it opens the port (a stable udev symlink),
sends the start-up commands, reads, stamps each sentence with the arrival of
its first byte on the monotonic clock minus the configured latency, and
hands body attitude samples to a sink. An unplugged device (read error) is
reopened with backoff; a silent one gets the start-up commands again and is
reopened when the silence lasts. Its `device_state` (drivers/device_state.py)
tells no device, silent (no bytes) and bad data (bytes, but no valid sample:
garbage, NaN, or the same values frozen for `frozen_s`) apart.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import reduce

from drivers.device_state import DeviceState, State
from onboard.core.attitude import AttitudeSample, to_body_sample
from onboard.core.rotations import IDENTITY_Q_XYZW, Quat
from onboard.core.sources import Backoff, Counters, DriverThread

log = logging.getLogger(__name__)

START_CHARS = b"$~@"
MAX_SENTENCE_BYTES = 256  # the longest real sentence ($QUATIMU) is ~110 bytes
DEFAULT_BAUD = 115200


def checksum(body: bytes) -> str:
    """XOR of every byte of `body` (start character included), as 2 hex digits."""
    return f"{reduce(lambda a, c: a ^ c, body, 0):02X}"


def command(text: str) -> bytes:
    """A framed command: command("version") == b"@version*3A\\r\\n"."""
    body = ("@" + text.lstrip("@")).encode("ascii")
    return body + b"*" + checksum(body).encode("ascii") + b"\r\n"


def startup_commands(divider: int) -> list[bytes]:
    return [command("mode,AC"), command("asc_out,QUATIMU"), command(f"divider,{divider}")]


@dataclass(frozen=True)
class QuatImu:
    """One `$QUATIMU` sentence. `t_ns`: arrival of its first byte (monotonic)."""

    t_ns: int
    seq: int
    q_xyzw: Quat  # sensor axes in the sensor's world, scalar last as sent
    accel_g: tuple[float, float, float]
    gyro_dps: tuple[float, float, float]
    mag: tuple[float, float, float]
    temperature_c: float


@dataclass(frozen=True)
class ParserStats:
    sentences: int = 0  # valid $QUATIMU samples
    replies: int = 0  # ~ replies with a valid checksum
    reply_errors: int = 0  # ... of which the device said ERROR
    other_sentences: int = 0  # valid $ sentences of another kind ($RPY before configuration)
    checksum_errors: int = 0  # framed lines whose checksum is missing or wrong
    malformed: int = 0  # good checksum, but fields that do not parse
    partial_lines: int = 0  # a sentence cut off (new start char, overlong, or reconnect)
    garbage_lines: int = 0  # terminated runs of bytes outside any sentence
    garbage_bytes: int = 0


class MyAhrsParser:
    """Bytes in, `QuatImu` samples out; everything else counted.

    `feed(data, t_ns)` takes one read's bytes and their arrival time. A
    sentence is stamped with the arrival of the read holding its start
    character, so a line split over several reads keeps its first stamp.
    """

    def __init__(self) -> None:
        self.stats = ParserStats()
        self._buf = bytearray()
        self._t_start_ns = 0
        self._in_sentence = False
        self._skipping = False  # the rest of an overlong line (already counted partial)
        self._garbage = 0  # bytes of the current garbage run
        self.last_reply: str | None = None

    def feed(self, data: bytes, t_ns: int) -> list[QuatImu]:
        out: list[QuatImu] = []
        for b in data:
            if b in START_CHARS:
                if self._in_sentence:
                    self._count(partial_lines=1)
                elif self._garbage:
                    self._end_garbage()
                self._buf = bytearray((b,))
                self._t_start_ns = t_ns
                self._in_sentence = True
                self._skipping = False
            elif b in (0x0D, 0x0A):  # \r or \n ends a line
                self._skipping = False
                if self._in_sentence:
                    sample = self._sentence(bytes(self._buf))
                    if sample is not None:
                        out.append(sample)
                    self._in_sentence = False
                    self._buf.clear()
                elif self._garbage:
                    self._end_garbage()
            elif self._in_sentence:
                self._buf.append(b)
                if len(self._buf) > MAX_SENTENCE_BYTES:
                    self._count(partial_lines=1)
                    self._in_sentence = False
                    self._skipping = True
                    self._buf.clear()
            elif not self._skipping:
                self._garbage += 1
        return out

    def reset(self) -> None:
        """The connection ended: an unfinished sentence is a partial line."""
        if self._in_sentence:
            self._count(partial_lines=1)
        elif self._garbage:
            self._end_garbage()
        self._in_sentence = False
        self._skipping = False
        self._buf.clear()

    # -- internals

    def _count(self, **deltas: int) -> None:
        s = self.stats
        self.stats = ParserStats(**{k: getattr(s, k) + deltas.get(k, 0)
                                    for k in s.__dataclass_fields__})

    def _end_garbage(self) -> None:
        self._count(garbage_lines=1, garbage_bytes=self._garbage)
        self._garbage = 0

    def _sentence(self, line: bytes) -> QuatImu | None:
        body, star, sent = line.rpartition(b"*")
        if not star or len(sent) != 2 or checksum(body) != sent.decode("ascii", "replace").upper():
            self._count(checksum_errors=1)
            return None
        text = body.decode("ascii", "replace")
        if text[0] == "~":
            self.last_reply = text
            error = len(text.split(",")) > 1 and text.split(",")[1].strip() == "ERROR"
            self._count(replies=1, reply_errors=int(error))
            if error:
                log.warning("myAHRS+ refused a command: %s", text)
            return None
        fields = text.split(",")
        if fields[0] != "$QUATIMU":
            self._count(other_sentences=1)
            return None
        try:
            values = [float(f) for f in fields[1:]]
        except ValueError:
            values = []
        if len(values) != 15 or not all(math.isfinite(v) for v in values):
            self._count(malformed=1)
            return None
        self._count(sentences=1)
        return QuatImu(
            t_ns=self._t_start_ns,
            seq=int(values[0]),
            q_xyzw=(values[1], values[2], values[3], values[4]),
            accel_g=(values[5], values[6], values[7]),
            gyro_dps=(values[8], values[9], values[10]),
            mag=(values[11], values[12], values[13]),
            temperature_c=values[14],
        )


@dataclass(frozen=True)
class LinkStats:
    opens: int = 0  # successful port opens
    open_failures: int = 0
    disconnects: int = 0  # read/write errors that closed the port (unplug)
    silences: int = 0  # start-up commands re-sent because no sample came
    reopens_for_silence: int = 0
    commands_sent: int = 0
    samples: int = 0  # body samples handed to the sink
    parser: ParserStats = ParserStats()


class MyAhrsDriver(DriverThread):
    """Reads a myAHRS+ on `port` and hands body attitude samples to `sink`.

    `serial_factory(port, baud, timeout)` opens the port (pyserial's
    `serial.Serial` by default). `on_reading` (optional) sees every raw
    `QuatImu` as well, in the driver thread.
    """

    def __init__(
        self,
        port: str,
        sink: Callable[[AttitudeSample], object],
        *,
        baud: int = DEFAULT_BAUD,
        divider: int = 1,
        latency_ms: float = 0.0,
        q_B_A_xyzw: Quat = IDENTITY_Q_XYZW,
        silence_s: float = 1.0,
        reopen_after_s: float = 3.0,
        reconnect_min_s: float = 0.1,
        reconnect_max_s: float = 2.0,
        read_timeout_s: float = 0.1,
        serial_factory: Callable[..., object] | None = None,
        on_reading: Callable[[QuatImu], object] | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        frozen_s: float = 0.5,
    ) -> None:
        super().__init__(f"myahrs:{port}")
        self.device_state = DeviceState("myAHRS+", port)
        # A real sensor's quaternion changes in its last digits every sample;
        # the same values this long are a hung sensor, not a still vehicle.
        self.frozen_ns = int(frozen_s * 1e9)
        self._frozen_q: Quat | None = None
        self._frozen_since_ns = 0
        self._is_frozen = False
        self.port = port
        self.sink = sink
        self.baud = baud
        self.divider = divider
        self.latency_ns = int(round(latency_ms * 1e6))
        self.q_B_A_xyzw = q_B_A_xyzw
        self.silence_ns = int(silence_s * 1e9)
        self.reopen_after_ns = int(reopen_after_s * 1e9)
        self.read_timeout_s = read_timeout_s
        self.backoff = Backoff(reconnect_min_s, reconnect_max_s)
        self.serial_factory = serial_factory
        self.on_reading = on_reading
        self.clock_ns = clock_ns
        self.parser = MyAhrsParser()
        self.counters: Counters[LinkStats] = Counters(LinkStats())
        self.last_reading: QuatImu | None = None
        self._serial: object | None = None  # the open port, for _interrupt only

    @property
    def stats(self) -> LinkStats:
        return self.counters.snapshot()

    # -- thread

    def _run(self) -> None:
        try:
            self._run_device()
        finally:
            self.device_state.set(State.CLOSED)

    def _run_device(self) -> None:
        while not self.stopping:
            ser = self._open()
            if ser is None:
                if self._sleep(self.backoff.next()):
                    break
                continue
            try:
                self._serve(ser)
            except OSError as e:  # serial.SerialException is an OSError: unplugged, I/O error
                if not self.stopping:
                    log.info("myAHRS+ %s: connection lost: %s", self.port, e)
                    self.device_state.set(State.NO_DEVICE, f"connection lost: {e}")
                    self.counters.bump(disconnects=1)
            finally:
                self._serial = None
                _close_quietly(ser)
                self.parser.reset()
                self.counters.set(parser=self.parser.stats)
            if not self.stopping and self._sleep(self.backoff.next()):
                break

    def _open(self) -> object | None:
        factory = self.serial_factory or _pyserial_factory
        try:
            ser = factory(self.port, self.baud, self.read_timeout_s)
        except (OSError, ValueError) as e:  # absent, busy, no permission, bad settings
            log.debug("myAHRS+ %s: cannot open: %s", self.port, e)
            self.device_state.set(State.NO_DEVICE, f"cannot open: {_short(e)}")
            self.counters.bump(open_failures=1)
            return None
        self._serial = ser
        self.device_state.set(State.OPEN)
        self.counters.bump(opens=1)
        log.info("myAHRS+ %s: opened", self.port)
        return ser

    def _serve(self, ser) -> None:
        self._configure(ser)
        last_sample_ns = self.clock_ns()
        last_config_ns = last_sample_ns
        bytes_since = 0  # bytes read since the last valid sample
        while not self.stopping:
            data = ser.read(max(1, ser.in_waiting))  # returns after read_timeout_s at most
            now_ns = self.clock_ns()
            if data:
                readings = self.parser.feed(data, now_ns)
                bytes_since += len(data)
                if readings and self._deliver(readings):
                    last_sample_ns = now_ns
                    bytes_since = 0
                    self.backoff.reset()
                self.counters.set(parser=self.parser.stats)
            silent_ns = now_ns - last_sample_ns
            if silent_ns >= self.silence_ns:
                self._no_samples(silent_ns, bytes_since)
            if silent_ns >= self.reopen_after_ns:
                log.info("myAHRS+ %s: no valid sample for %.1f s, reopening", self.port,
                         silent_ns * 1e-9)
                self.counters.bump(reopens_for_silence=1)
                return
            if silent_ns >= self.silence_ns and now_ns - last_config_ns >= self.silence_ns:
                # A device that reset (power glitch) forgot the volatile settings.
                self.counters.bump(silences=1)
                self._configure(ser)
                last_config_ns = now_ns

    def _configure(self, ser) -> None:
        for cmd in startup_commands(self.divider):
            ser.write(cmd)
        ser.flush()
        self.counters.bump(commands_sent=3)

    def _no_samples(self, silent_ns: int, bytes_since: int) -> None:
        """No valid sample for `silent_ns`: silent, or bad data when bytes came."""
        p = self.parser.stats
        if self._is_frozen and bytes_since:
            return  # valid sentences, but frozen values: told in _frozen
        if bytes_since:
            self.device_state.set(State.BAD_DATA, (
                f"{bytes_since} bytes but no valid sample for {silent_ns * 1e-9:.1f} s "
                f"(checksum errors {p.checksum_errors}, malformed {p.malformed}, "
                f"garbage lines {p.garbage_lines})"))
        else:
            self.device_state.set(State.SILENT, f"no bytes for {silent_ns * 1e-9:.1f} s")

    def _deliver(self, readings: list[QuatImu]) -> int:
        samples = []
        for r in readings:
            self.last_reading = r
            if self.on_reading is not None:
                self.on_reading(r)
            if self._frozen(r):
                continue
            sample = to_body_sample(r.t_ns - self.latency_ns, r.q_xyzw, self.q_B_A_xyzw)
            if sample is not None:
                samples.append(sample)
        if samples:  # told before the samples go: "recovered" precedes the first good one
            self.device_state.set(State.STREAMING)
        for sample in samples:
            self.sink(sample)
        self.counters.bump(samples=len(samples))
        return len(samples)

    def _frozen(self, r: QuatImu) -> bool:
        """True while the values have not changed for `frozen_ns` (not delivered)."""
        if r.q_xyzw != self._frozen_q:
            self._frozen_q, self._frozen_since_ns = r.q_xyzw, r.t_ns
            self._is_frozen = False
            return False
        if r.t_ns - self._frozen_since_ns < self.frozen_ns:
            return False
        self._is_frozen = True
        self.device_state.set(State.BAD_DATA, (
            f"values frozen for {(r.t_ns - self._frozen_since_ns) * 1e-9:.1f} s "
            f"(q = {', '.join(f'{c:g}' for c in r.q_xyzw)})"))
        return True

    def _interrupt(self) -> None:
        ser = self._serial
        cancel = getattr(ser, "cancel_read", None)
        if cancel is not None:
            cancel()


def _pyserial_factory(port: str, baud: int, timeout_s: float):
    import serial  # pyserial: a core dependency, imported where the port opens

    return serial.Serial(port, baud, timeout=timeout_s, write_timeout=1.0, exclusive=True)


def _short(e: BaseException) -> str:
    """pyserial repeats itself ("[Errno 2] could not open port X: [Errno 2]
    No such file or directory: 'X'"): the OS's words for the errno."""
    errno_ = getattr(e, "errno", None)
    return os.strerror(errno_) if isinstance(errno_, int) and errno_ > 0 else str(e)


def _close_quietly(ser) -> None:
    try:
        ser.close()
    except OSError:  # closing a vanished device may fail; it is gone either way
        log.debug("close failed", exc_info=True)
