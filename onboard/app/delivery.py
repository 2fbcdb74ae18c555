"""What each output delivered, for the run's summary: messages sent, the
link's state, whether anyone answered (over UDP a send succeeds with nobody
listening, so only a message back proves a receiver)."""

from __future__ import annotations

from typing import Any


def delivery_lines(stats: dict[str, dict[str, Any]]) -> list[str]:
    """One line per output from OutputGroup.stats() ("mavlink", "zenoh")."""
    lines = []
    m = stats.get("mavlink")
    if m is not None:
        by_type = ", ".join(f"{k} {v}" for k, v in sorted(m.get("sent_by_type", {}).items()))
        heard = m.get("received", 0)
        peer = (f"{heard} messages back from the peer" if heard
                else "nothing back from the peer (nobody may be receiving)")
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
