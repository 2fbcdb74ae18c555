"""What each output delivered, for the run's summary: messages sent, the
link's state, whether anyone answered (over UDP a send succeeds with nobody
listening, so only a message back proves a receiver)."""

from __future__ import annotations

import logging
from typing import Any

log = logging.getLogger(__name__)


def delivery_lines(stats: dict[str, dict[str, Any]]) -> list[str]:
    """One line per output from OutputGroup.stats() ("mavlink", "zenoh")."""
    lines = []
    m = stats.get("mavlink")
    if m is not None:
        by_type = ", ".join(f"{k} {v}" for k, v in sorted(m.get("sent_by_type", {}).items()))
        heard = m.get("received", 0)
        peer = (f"{heard} messages back from the peer" if heard
                else "the autopilot link is shared (its state: the device line)"
                if m.get("shared_link") else "nothing back from the peer (nobody may be receiving)")
        lines.append(
            f"mavlink     {m.get('poses_sent', 0)} poses sent, {m.get('not_sent', 0)} found the "
            f"link down; link {'up' if m.get('link_up') else 'down'} at the end "
            f"({m.get('link_opens', 0)} opens, {m.get('link_errors', 0)} errors); {peer}"
            + (f"; sent {by_type}" if by_type else ""))
    z = stats.get("zenoh")
    if z is not None:
        lines.append(
            f"zenoh       {z.get('poses_published', 0)} poses, {z.get('keyframes_published', 0)} "
            f"key frames published; dropped {z.get('dropped_poses', 0)} poses, "
            f"{z.get('dropped_keyframes', 0)} key frames; {z.get('errors', 0)} errors; "
            f"session {'open' if z.get('connected') else 'closed'}")
    return lines


class DeliveryWatch:
    """Tells once, during the run, a MAVLink output that sends but hears
    nothing back after `after_s` (over UDP a send succeeds with nobody
    listening; a live autopilot sends its HEARTBEAT at 1 Hz)."""

    def __init__(self, after_s: float = 5.0) -> None:
        self.after_s = after_s
        self.told = False
        self._since: float | None = None

    def check(self, outputs: Any, now_s: float) -> None:
        if self.told:
            return
        for out in getattr(outputs, "outputs", ()):
            if type(out).__name__ != "MavlinkOutput":
                continue
            s = out.stats()
            if s.get("shared_link") or s.get("received", 0):
                self.told = True  # heard: nothing to tell, ever
                return
            if not s.get("poses_sent", 0) and not s.get("heartbeats", 0):
                return
            self._since = now_s if self._since is None else self._since
            if now_s - self._since >= self.after_s:
                self.told = True
                log.warning("MAVLink %s: %d poses and %d heartbeats sent, nothing came back "
                            "in %.0f s: nobody may be receiving", out.cfg.connect,
                            s.get("poses_sent", 0), s.get("heartbeats", 0), now_s - self._since)
