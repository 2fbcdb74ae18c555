"""zenoh sessions for the vehicle, the ground station and the router: the
configuration from `[zenoh]` (endpoints, scouting, TLS), opening (in the
background when a client has to wait for its router), and the bounded-queue
worker thread the publisher runs on.

Nothing listens or scouts beyond the configured endpoints: multicast and
gossip scouting are off unless `multicast_scouting`, and `listen` is exactly
the configured list (zenoh's own default would listen on every interface).
Connecting retries for ever (`connect/timeout_ms = -1`, every 0.25-1 s): a
client waits in `zenoh.open` until its router answers, a peer opens at once
and connects when the router appears; both reconnect on their own after the
router went away.

TLS (`tls_root_ca` set): mutual TLS on both sides of every `tls/...`
endpoint: this node shows `tls_certificate` (signed by the fleet CA) and
accepts only peers whose certificate the fleet CA signed (docs/fleet.md).
"""

from __future__ import annotations

import json
import logging
import threading
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any, Generic, TypeVar

import zenoh

from onboard import NislamError
from onboard.outputs.settings import ZenohConfig
from onboard.outputs.wake import Wake

log = logging.getLogger(__name__)

T = TypeVar("T")

RETRY = {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}


def key_prefix(vehicle: str) -> str:
    return f"nislam/{vehicle}"


def priority(name: str) -> zenoh.Priority:
    """zenoh.Priority from a ZENOH_PRIORITIES name ("interactive_high", ...)."""
    return getattr(zenoh.Priority, name.upper())


def tls_settings(root_ca: str, certificate: str, private_key: str,
                 origin: str = "[zenoh]") -> dict[str, Any] | None:
    """`transport/link/tls` for mutual TLS, or None without `root_ca`.
    NislamError when a file is missing (named by its key)."""
    if not root_ca:
        return None
    files = {"tls_root_ca": root_ca, "tls_certificate": certificate,
             "tls_private_key": private_key}
    for key, path in files.items():
        if not path:
            raise NislamError(f"{origin} tls_root_ca is set but {key} is empty (mutual TLS "
                              f"needs this node's certificate and key)")
        if not Path(path).is_file():
            raise NislamError(f"{origin} {key}: no such file {path}")
    return {
        "root_ca_certificate": root_ca,
        "enable_mtls": True,
        "listen_certificate": certificate, "listen_private_key": private_key,
        "connect_certificate": certificate, "connect_private_key": private_key,
    }


def base_config(mode: str, connect: tuple[str, ...] | list[str],
                listen: tuple[str, ...] | list[str], scouting: bool,
                tls: dict[str, Any] | None) -> zenoh.Config:
    conf = zenoh.Config()
    try:
        for key, value in (("mode", mode), ("connect/endpoints", list(connect)),
                           ("listen/endpoints", list(listen)),
                           ("scouting/multicast/enabled", scouting),
                           ("scouting/gossip/enabled", scouting),
                           ("connect/timeout_ms", -1), ("connect/retry", RETRY)):
            conf.insert_json5(key, json.dumps(value))
        if tls is not None:
            conf.insert_json5("transport/link/tls", json.dumps(tls))
    except zenoh.ZError as e:
        raise NislamError(f"zenoh configuration refused: {e}") from None
    return conf


def session_config(
    cfg: ZenohConfig,
    mode: str | None = None,
    connect: tuple[str, ...] | None = None,
    listen: tuple[str, ...] | None = None,
) -> zenoh.Config:
    """A zenoh.Config from [zenoh], with optional overrides (command-line flags)."""
    return base_config(
        mode or cfg.mode, cfg.connect if connect is None else connect,
        cfg.listen if listen is None else listen, cfg.multicast_scouting,
        tls_settings(cfg.tls_root_ca, cfg.tls_certificate, cfg.tls_private_key))


def open_session(conf: zenoh.Config) -> zenoh.Session:
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        raise NislamError(f"cannot open the zenoh session: {e}") from None


def open_waiting(conf: zenoh.Config, stop: threading.Event,
                 on_wait: Callable[[], None] | None = None,
                 poll_s: float = 1.0) -> zenoh.Session | None:
    """Open on a helper thread (a client blocks until its router answers);
    None when `stop` is set first. `on_wait` runs once if it takes > poll_s."""
    box: list[Any] = []
    done = threading.Event()

    def run() -> None:
        try:
            box.append(zenoh.open(conf))
        except zenoh.ZError as e:
            box.append(NislamError(f"cannot open the zenoh session: {e}"))
        done.set()

    threading.Thread(target=run, name="zenoh-open", daemon=True).start()
    if not done.wait(poll_s) and on_wait is not None:
        on_wait()
    while not done.wait(0.1):
        if stop.is_set():
            return None
    if isinstance(box[0], Exception):
        raise box[0]
    return box[0]


class Worker(Generic[T]):
    """A thread fed through a bounded deque that drops its oldest item.
    `tick()` (optional) runs after every wake-up and returns the seconds until
    it wants to run again."""

    def __init__(self, name: str, handle: Callable[[T], None], maxlen: int,
                 tick: Callable[[], float] | None = None) -> None:
        self._handle = handle
        self._tick = tick
        self._items: deque[T] = deque(maxlen=maxlen)
        self.wakeup = Wake()  # never makes the loop wait (onboard/outputs/wake.py)
        self._stopping = False
        self.dropped = 0
        self.errors = 0
        self._failing = False
        self._name = name
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def put(self, item: T) -> None:
        # deque.append is atomic and drops the oldest when full; one producer
        # (the loop) counts the drops.
        if len(self._items) == self._items.maxlen:
            self.dropped += 1
        self._items.append(item)
        self.wakeup.set()

    def wake(self) -> None:
        """Run `tick()` now rather than when it asked to."""
        self.wakeup.set()

    def stop(self, timeout_s: float) -> bool:
        """Handle what is queued, then stop; False if the thread is still busy."""
        self._stopping = True
        self.wakeup.set_now()
        if self._thread.is_alive():
            self._thread.join(timeout_s)
        return not self._thread.is_alive()

    def _run(self) -> None:
        wait_s: float | None = 0.0 if self._tick else None
        while True:
            if not self._items and not self._stopping:
                self.wakeup.wait(wait_s)
            stopping = self._stopping  # read before the queue: what came before stop goes out
            while self._items:
                self._guard(self._handle, self._items.popleft())  # atomic: no item lost
            if self._tick is not None:
                wait_s = self._guard(self._tick)
                wait_s = 1.0 if wait_s is None else max(0.0, wait_s)
            if stopping:
                return

    def _guard(self, fn: Callable[..., Any], *args: Any) -> Any:
        """Run fn; count and log (once per spell) what it raises."""
        try:
            out = fn(*args)
        except Exception as e:  # noqa: BLE001 - zenoh errors, encoding bugs: keep publishing
            self.errors += 1
            if not self._failing:
                self._failing = True
                log.warning("%s: %s: %s (further errors counted, not logged)",
                            self._name, type(e).__name__, e)
            return None
        if self._failing:
            self._failing = False
            log.info("%s: working again after %d errors", self._name, self.errors)
        return out
