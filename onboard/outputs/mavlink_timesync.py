"""Our own TIMESYNC requests: the autopilot's clock offset and the link's round
trip, pure (no I/O; onboard.outputs.mavlink sends and receives).

MAVLink TIMESYNC (common.xml): a request carries tc1 = 0 and ts1 = the
sender's time [ns]; the answer carries tc1 = the responder's time when it
answered and ts1 copied from the request. ArduPilot (GCS_MAVLINK::
handle_timesync) and PX4 (MavlinkTimesync) both answer any request. With t0 =
our ts1, t1 = the answer's arrival on our clock and tc = the autopilot's tc1:

    rtt    = t1 - t0
    offset = tc - (t0 + rtt / 2)          autopilot clock minus ours [ns]

exact when both directions take equally long. Queueing (a busy link, our
sender polling its port, the autopilot's scheduler) only ever adds time, and
adds it unequally, so the answers with the least round trip carry the least
error: the estimate is the offset of the least-RTT answer among the last
`window` (NTP's clock filter, Mills 1991, on the same reasoning). The window
is short (16 answers, 16 s at the steady 1 Hz) because the two crystals
drift apart by tens of ppm: 20 ppm over 16 s is 0.3 ms.

The link's one-way time (for the capture-to-arrival latency) is half the
least round trip: TIMESYNC messages are short, so on a serial link the pose's
own transmit time (its bytes x 10 / baud) is added by the caller.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

BURST = 10  # requests at BURST_PERIOD_S first: an estimate within a second
BURST_PERIOD_S = 0.1
PERIOD_S = 1.0  # then one a second (PX4's own steady rate)
WINDOW = 16
PENDING = 32  # requests we remember (a late answer to an older one still counts)
MAX_RTT_S = 1.0  # an answer later than this is not a clock measurement
# MAVLink 2 packet sizes (header 10 + payload + CRC 2, extensions included): on a
# serial link a pose takes bytes x 10 / baud to go out, which the short
# TIMESYNC round trip does not show.
PACKET_BYTES = {"odometry": 244, "vision_position": 129 + 128}


@dataclass(frozen=True)
class TimesyncEstimate:
    offset_ns: int  # the autopilot's clock minus ours
    rtt_ns: int  # the least round trip in the window (the estimate's)
    rtt_median_ns: int
    samples: int  # answers in the window
    answers: int  # answers matched since start

    def as_dict(self) -> dict[str, float | int]:
        return {"offset_ms": self.offset_ns / 1e6, "rtt_min_ms": self.rtt_ns / 1e6,
                "rtt_median_ms": self.rtt_median_ns / 1e6, "samples": self.samples,
                "answers": self.answers}


class TimesyncClock:
    """When to ask, and what the answers say. `due(now_ns)` -> the ts1 to send
    (None: not yet); `on_answer(tc1, ts1, t_rx_ns)` -> True when it answered
    one of ours."""

    def __init__(self, window: int = WINDOW) -> None:
        self._pending: deque[int] = deque(maxlen=PENDING)
        self._samples: deque[tuple[int, int]] = deque(maxlen=window)  # (rtt, offset)
        self._next_ns: int | None = None
        self.sent = 0
        self.answers = 0
        self.ignored = 0  # answers to someone else's request, or too late

    def due(self, now_ns: int) -> int | None:
        if self._next_ns is not None and now_ns < self._next_ns:
            return None
        period = BURST_PERIOD_S if self.sent < BURST else PERIOD_S
        self._next_ns = now_ns + int(period * 1e9)
        self._pending.append(now_ns)
        self.sent += 1
        return now_ns

    def pending(self, ts1_ns: int) -> bool:
        """Request `ts1_ns` not answered yet."""
        return ts1_ns in self._pending

    def next_due_ns(self) -> int | None:
        return self._next_ns

    def on_answer(self, tc1_ns: int, ts1_ns: int, t_rx_ns: int) -> bool:
        if ts1_ns not in self._pending:
            self.ignored += 1
            return False
        self._pending.remove(ts1_ns)
        rtt = t_rx_ns - ts1_ns
        if rtt < 0 or rtt > MAX_RTT_S * 1e9:
            self.ignored += 1
            return False
        self._samples.append((rtt, tc1_ns - (ts1_ns + rtt // 2)))
        self.answers += 1
        return True

    def estimate(self) -> TimesyncEstimate | None:
        samples = list(self._samples)
        if not samples:
            return None
        rtt, offset = min(samples)
        med = int(np.median([r for r, _ in samples]))
        return TimesyncEstimate(int(offset), int(rtt), med, len(samples), self.answers)

    def one_way_s(self) -> float | None:
        est = self.estimate()
        return None if est is None else est.rtt_ns / 2e9
