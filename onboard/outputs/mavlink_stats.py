"""The MAVLink sender's counters and the shared-link protocol
(onboard.outputs.mavlink re-exports both)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol


@dataclass
class MavlinkStats:
    """Counters of the sender thread (read them with `MavlinkOutput.stats()`)."""

    results: int = 0
    dropped: int = 0  # results dropped from the full queue
    poses_sent: int = 0
    not_sent: int = 0  # poses that found the link down
    heartbeats: int = 0
    statustexts: int = 0
    timesync_replies: int = 0
    link_errors: int = 0
    link_opens: int = 0
    link_up: bool = False
    signature_rejects: int = 0  # received messages unsigned or wrongly signed (signing on)
    timesync_requests: int = 0  # our own TIMESYNC requests sent (mavlink_timesync)
    timesync_answers: int = 0  # answers to them
    untrusted_sent: int = 0  # poses sent for a result the tracker did not trust (must stay 0)
    sent_by_type: dict[str, int] = field(default_factory=dict)
    received: int = 0  # messages from the peer (0 over UDP: nobody may be listening)


class SharedLink(Protocol):
    """A MAVLink connection owned by someone else (drivers.fc_link.FcLink):
    one link per autopilot, shared with the autopilot attitude source."""

    def send(self, build: Callable[[Any], object]) -> bool:
        """Run build(mav) under the link's write lock; False when it is down."""
        ...

    def add_listener(self, callback: Callable[[Any, int], object],
                     types: Iterable[str] | None = None) -> Callable[[], None]:
        """callback(msg, t_arrival_ns) for messages of `types`; returns a remover."""
        ...
