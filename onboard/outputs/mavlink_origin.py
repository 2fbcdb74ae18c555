"""Where the feed's local frame starts, told to the autopilot.

- `OriginHandshake`: without GPS the autopilot's EKF has no global origin, so
  the feed offers one (`[mavlink] set_origin`, origin_* keys):
  SET_GPS_GLOBAL_ORIGIN, repeated each second until the autopilot confirms
  with GPS_GLOBAL_ORIGIN, 5 tries at most; with `set_home` also
  SET_HOME_POSITION at the same place. ArduPilot has no handler for
  SET_HOME_POSITION (it sets home itself, at arming or from the origin), so
  it is off by default. Pure: the link thread (onboard.outputs.mavlink) asks
  what to send and when.
- `ResetCounterStore`: each process puts its world origin at its first pose,
  so a restarted service starts a new local frame. The autopilot learns that
  from `reset_counter` (ArduPilot's VOXL backend re-anchors on a change), so
  a new process must never reuse the counter of the one before: the last
  counter sent is kept in a small file under the service's state directory
  and the new process starts one above it. Without a writable directory the
  start is taken from the clock (a 1 in 256 chance to repeat the previous
  process's last counter), with a warning.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import Any

from onboard.outputs.settings import MavlinkConfig

log = logging.getLogger(__name__)

RETRY_S = 1.0
MAX_TRIES = 5
COUNTER_FILE = "mavlink_reset_counter"


class OriginHandshake:
    def __init__(self, cfg: MavlinkConfig) -> None:
        self.cfg = cfg
        self.done = not cfg.set_origin
        self.tries = 0
        self.next_s = 0.0  # monotonic time of the next try

    def due(self, now_s: float) -> bool:
        return not self.done and now_s >= self.next_s

    def messages(self, now_s: float, t_us: int) -> list[tuple[str, tuple[Any, ...]]]:
        """This try's messages as (pymavlink message name, send arguments);
        the next try is a second later, none after the last."""
        c = self.cfg
        lat, lon = round(c.origin_lat_deg * 1e7), round(c.origin_lon_deg * 1e7)
        alt = round(c.origin_alt_m * 1e3)
        self.tries += 1
        self.next_s = now_s + RETRY_S
        if self.tries >= MAX_TRIES:
            self.done = True
        out: list[tuple[str, tuple[Any, ...]]] = [
            ("set_gps_global_origin", (c.system_id, lat, lon, alt, t_us))]
        if c.set_home:
            out.append(("set_home_position", (c.system_id, lat, lon, alt, 0.0, 0.0, 0.0,
                                              [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, t_us)))
        return out

    def on_confirmed(self) -> None:
        """The autopilot sent GPS_GLOBAL_ORIGIN."""
        if not self.done:
            self.done = True
            log.info("autopilot confirmed the EKF origin")


def state_directory(configured: str, env: dict[str, str] | None = None) -> Path:
    """The service's state directory: `configured` when set, else systemd's
    $STATE_DIRECTORY (its first entry), else $XDG_STATE_HOME/nislam, else
    ~/.local/state/nislam."""
    if configured:
        return Path(configured).expanduser()
    env = os.environ if env is None else env
    systemd = env.get("STATE_DIRECTORY", "")
    if systemd:
        return Path(systemd.split(":")[0])
    xdg = env.get("XDG_STATE_HOME", "")
    base = Path(xdg) if xdg else Path(env.get("HOME", "~")).expanduser() / ".local" / "state"
    return base / "nislam"


class ResetCounterStore:
    """The last reset_counter sent, kept across processes in `directory`."""

    def __init__(self, directory: Path) -> None:
        self.path = Path(directory) / COUNTER_FILE
        self.saved: int | None = None
        self._failed = False

    def start_counter(self, clock_s: float | None = None) -> int:
        """The counter of this process's first pose: one above the last one
        sent by any earlier process, or from the clock when none is known."""
        try:
            last = int(self.path.read_text().split()[0]) % 256
        except FileNotFoundError:
            last = None
        except (OSError, ValueError, IndexError) as e:
            log.warning("cannot read %s (%s); reset_counter starts from the clock", self.path, e)
            last = None
        if last is not None:
            return (last + 1) % 256
        t = time.time() if clock_s is None else clock_s
        return int(t * 10.0) % 256  # tenths of a second: two quick restarts still differ

    def save(self, counter: int) -> None:
        """Keep `counter` (atomically; a failure is logged once, never raised)."""
        if counter == self.saved:
            return
        tmp = self.path.with_name(self.path.name + ".tmp")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(f"{counter}\n")
            os.replace(tmp, self.path)
        except OSError as e:
            if not self._failed:
                log.warning("cannot keep reset_counter in %s (%s): a restart may reuse it",
                            self.path, e.strerror or e)
                self._failed = True
            return
        self.saved = counter
