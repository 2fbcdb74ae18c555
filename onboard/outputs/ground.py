"""`nislam ground`: the fleet's ground station.

Follows every vehicle under `nislam/*/` on one zenoh session (a client of
the fleet's router): pose, status and key frames by wildcard subscriptions,
vehicles discovered by their liveliness token `nislam/<id>/alive` (history:
those already up are reported at once) or their first message. For each
vehicle discovered it fetches the map through the vehicle's queryable (late
join), and again whenever a status's `map_digest` differs from the digest of
what it holds (key frames lost while a router was down, or re-published
after a refinement), at most every `REFETCH_S` per vehicle.

A vehicle is its id. Each run of a vehicle's service has a random `boot`
(in pose and status, and as the attachment of key frames): a new boot is a
restart of the same vehicle, whose key-frame ids start again, so the map and
trajectory held so far are kept aside as an earlier boot (written as
`<id>.boot<N>.ply`) and the vehicle starts afresh; messages of an earlier
boot still in flight are ignored.

Threads: zenoh's callbacks only decode and queue; a fetch thread runs the
map queries; the caller's thread (`run`) owns all state, prints the table
and writes the files. The fleet status queryable (`nislam/@fleet/status`)
answers from a JSON snapshot the caller's thread refreshes.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from onboard.outputs.fleet_files import Earlier, table_lines, write_fleet
from onboard.outputs.mapcodec import MapCodecError, MapKeyframe, decode_keyframe, map_digest
from onboard.outputs.router import FLEET_STATUS_KEY

log = logging.getLogger(__name__)

REFETCH_S = 2.0  # a vehicle's map is fetched again at most this often
SNAPSHOT_S = 0.5  # the fleet status queryable's answer is this fresh
LATENCY_WINDOW = 64  # poses in the latency median


@dataclass
class Vehicle:
    """What the ground holds about one vehicle (its current boot)."""

    vid: str
    boot: str | None = None
    past_boots: set[str] = field(default_factory=set)
    earlier: list[Earlier] = field(default_factory=list)
    restarts: int = 0
    alive: bool = False
    poses: int = 0
    statuses: int = 0
    last_state: str = "unknown"
    last_status: dict[str, Any] = field(default_factory=dict)
    keyframes: dict[int, MapKeyframe] = field(default_factory=dict)
    crcs: dict[int, int] = field(default_factory=dict)
    trajectory: list[tuple[float, float, float, float]] = field(default_factory=list)
    bytes: dict[str, int] = field(default_factory=lambda: {"pose": 0, "status": 0, "map": 0})
    latency_s: list[float] = field(default_factory=list)
    first_seen_s: float = 0.0
    last_seen_s: float = 0.0
    fetching: bool = False
    behind: bool = False  # its last status names a map other than ours (set per status and fetch)
    last_fetch_s: float = -1e9
    fetches: int = 0
    period_poses: int = 0  # poses since the last table

    @property
    def map_points(self) -> int:
        return sum(kf.num_points for kf in self.keyframes.values())

    def digest(self) -> str:
        return map_digest(self.crcs)

    def summary(self) -> dict[str, Any]:
        span = max(self.last_seen_s - self.first_seen_s, 1e-9)
        lat = sorted(self.latency_s)
        return {
            "keyframes": len(self.keyframes), "poses": self.poses,
            "map_points": self.map_points, "last_state": self.last_state,
            "alive": self.alive, "boot": self.boot, "restarts": self.restarts,
            "statuses": self.statuses, "map_fetches": self.fetches,
            "map_digest": self.digest(),
            "latency_ms_median": lat[len(lat) // 2] * 1e3 if lat else None,
            "bytes": dict(self.bytes),
            "bytes_per_s": {k: v / span for k, v in self.bytes.items()},
            "keyframe_crc32": {str(k): self.crcs[k] for k in sorted(self.crcs)},
        }


def _vid(key: zenoh.KeyExpr) -> str:
    return str(key).split("/")[1]


def _attachment(sample: zenoh.Sample) -> str | None:
    att = sample.attachment
    return None if att is None else att.to_string()


class GroundStation:
    """The fleet as seen on `session`; call `step()` repeatedly (or `run()`)."""

    def __init__(self, session: zenoh.Session, fetch_timeout_s: float = 10.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.session = session
        self.clock = clock
        self.fetch_timeout_s = fetch_timeout_s
        self.vehicles: dict[str, Vehicle] = {}
        self.events: queue.Queue[tuple[Any, ...]] = queue.Queue()
        self._fetch_q: queue.Queue[str | None] = queue.Queue()
        self._snapshot = json.dumps({"vehicles": {}})
        self._fetcher = threading.Thread(target=self._fetch_loop, name="ground-fetch",
                                         daemon=True)
        self._fetcher.start()
        s = session
        self._entities = [
            s.declare_subscriber("nislam/*/pose", self._on_json("pose")),
            s.declare_subscriber("nislam/*/status", self._on_json("status")),
            s.declare_subscriber("nislam/*/map/keyframe/*", self._on_keyframe),
            s.liveliness().declare_subscriber("nislam/*/alive", self._on_alive, history=True),
            s.declare_queryable(FLEET_STATUS_KEY, self._on_fleet_query),
        ]

    def close(self) -> None:
        for entity in self._entities:
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass
        self._fetch_q.put(None)
        self._fetcher.join(self.fetch_timeout_s + 1.0)

    # ------------------------------------------------------------ zenoh threads
    def _on_json(self, kind: str) -> Callable[[zenoh.Sample], None]:
        def callback(sample: zenoh.Sample) -> None:
            raw = sample.payload.to_bytes()
            try:
                msg = json.loads(raw)
            except ValueError as e:
                log.warning("bad %s message on %s: %s", kind, sample.key_expr, e)
                return
            self.events.put((kind, _vid(sample.key_expr), msg, len(raw), time.time()))
        return callback

    def _on_keyframe(self, sample: zenoh.Sample) -> None:
        raw = sample.payload.to_bytes()
        try:
            kf = decode_keyframe(raw)
        except MapCodecError as e:
            log.warning("bad key frame on %s: %s", sample.key_expr, e)
            return
        self.events.put(("keyframe", _vid(sample.key_expr), (kf, zlib.crc32(raw)),
                         len(raw), _attachment(sample)))

    def _on_alive(self, sample: zenoh.Sample) -> None:
        self.events.put(("alive", _vid(sample.key_expr), sample.kind == zenoh.SampleKind.PUT,
                         0, None))

    def _on_fleet_query(self, query: zenoh.Query) -> None:
        query.reply(FLEET_STATUS_KEY, self._snapshot, encoding=zenoh.Encoding.APPLICATION_JSON)

    def _fetch_loop(self) -> None:
        while True:
            vid = self._fetch_q.get()
            if vid is None:
                return
            got: list[tuple[MapKeyframe, int, str | None]] = []
            try:
                replies = self.session.get(f"nislam/{vid}/map/**", timeout=self.fetch_timeout_s,
                                           priority=zenoh.Priority.DATA_LOW)
                for reply in replies:
                    if reply.ok is None:
                        continue
                    raw = reply.ok.payload.to_bytes()
                    try:
                        got.append((decode_keyframe(raw), zlib.crc32(raw),
                                    _attachment(reply.ok)))
                    except MapCodecError as e:
                        log.warning("bad key frame from %s: %s", reply.ok.key_expr, e)
            except zenoh.ZError as e:
                log.warning("map query of %s failed: %s", vid, e)
            self.events.put(("fetched", vid, got, 0, None))

    # ------------------------------------------------------------ the caller's thread
    def vehicle(self, vid: str) -> Vehicle:
        v = self.vehicles.get(vid)
        if v is None:
            now = self.clock()
            v = self.vehicles[vid] = Vehicle(vid, first_seen_s=now, last_seen_s=now)
            log.info("vehicle %s discovered", vid)
            self._request_fetch(v)  # late join: whatever it already mapped
        return v

    def _request_fetch(self, v: Vehicle) -> None:
        if not v.fetching:
            v.fetching = True
            v.last_fetch_s = self.clock()
            v.fetches += 1
            self._fetch_q.put(v.vid)

    def _current(self, v: Vehicle, boot: str | None) -> bool:
        """False for a message of an earlier boot; a new boot restarts `v`."""
        if boot is None or boot == v.boot:
            return True
        if boot in v.past_boots:
            return False
        if v.boot is not None:
            v.past_boots.add(v.boot)
            v.earlier.append(Earlier(v.boot, dict(v.keyframes), list(v.trajectory)))
            v.keyframes, v.crcs, v.trajectory = {}, {}, []
            v.restarts += 1
            log.info("vehicle %s restarted (boot %s -> %s): one vehicle, a new map",
                     v.vid, v.boot, boot)
        v.boot = boot
        return True

    def step(self, timeout_s: float) -> bool:
        """Handle one event (waiting up to timeout_s); False if none came."""
        self._refetch_due()
        try:
            kind, vid, item, size, extra = self.events.get(timeout=timeout_s)
        except queue.Empty:
            return False
        v = self.vehicle(vid)
        v.last_seen_s = self.clock()
        if kind == "pose":
            self._pose(v, item, size, extra)
        elif kind == "status":
            self._status(v, item, size)
        elif kind == "keyframe":
            v.bytes["map"] += size
            if self._current(v, extra):
                kf, crc = item
                v.keyframes[kf.keyframe_id] = kf
                v.crcs[kf.keyframe_id] = crc
                v.behind = self._behind(v)
        elif kind == "alive":
            v.alive = item
        elif kind == "fetched":
            v.fetching = False
            for kf, crc, boot in item:
                if self._current(v, boot):
                    v.keyframes[kf.keyframe_id] = kf
                    v.crcs[kf.keyframe_id] = crc
            v.behind = self._behind(v)
        return True

    def _refetch_due(self) -> None:
        """A vehicle whose last status says its map is ahead of ours is
        fetched again once `REFETCH_S` has passed since the last fetch,
        without waiting for another status: key frames put while a router
        was down are lost on the wire, and a vehicle about to land may send
        no further status (a router restarted under load: 8 of 9 key frames)."""
        now = self.clock()
        for v in self.vehicles.values():
            if v.behind and not v.fetching and now - v.last_fetch_s > REFETCH_S:
                self._request_fetch(v)

    @staticmethod
    def _behind(v: Vehicle) -> bool:
        return v.last_status.get("map_digest") not in (None, v.digest())

    def _pose(self, v: Vehicle, m: dict[str, Any], size: int, recv_unix_s: float) -> None:
        v.bytes["pose"] += size
        if not self._current(v, m.get("boot")):
            return
        v.poses += 1
        v.period_poses += 1
        sent = m.get("sent_unix_s")
        if isinstance(sent, (int, float)):
            v.latency_s.append(recv_unix_s - sent)
            del v.latency_s[:-LATENCY_WINDOW]
        if m.get("trusted") and m.get("p_W_m") is not None:
            x, y, z = m["p_W_m"]
            v.trajectory.append((float(m["t_s"]), float(x), float(y), float(z)))

    def _status(self, v: Vehicle, m: dict[str, Any], size: int) -> None:
        v.bytes["status"] += size
        if not self._current(v, m.get("boot")):
            return
        v.statuses += 1
        v.last_status = m
        v.last_state = str(m.get("state", "unknown"))
        v.behind = self._behind(v)
        if v.behind and self.clock() - v.last_fetch_s > REFETCH_S:
            self._request_fetch(v)

    def summary(self) -> dict[str, Any]:
        return {"vehicles": {vid: self.vehicles[vid].summary() for vid in sorted(self.vehicles)}}

    def refresh_snapshot(self) -> None:
        self._snapshot = json.dumps(self.summary(), allow_nan=False)

    def settled(self) -> bool:
        """Every vehicle's map agrees with its last status, no fetch pending."""
        return all(not v.fetching and v.last_status.get("map_digest") in (None, v.digest())
                   for v in self.vehicles.values())


@dataclass
class GroundResult:
    summary: dict[str, Any]
    files: list[Path]


def run_ground(station: GroundStation, out_dir: Path, stop: threading.Event,
               seconds: float | None = None, emit: Callable[[str], None] = print,
               table_period_s: float = 1.0, save_now: threading.Event | None = None,
               settle_s: float = 5.0) -> GroundResult:
    """Follow the fleet until `stop` (or `seconds`), print the table every
    `table_period_s` (0: never), write the files on exit and whenever
    `save_now` is set.
    At the end it waits up to `settle_s` for maps still being fetched."""
    start = time.monotonic()
    end = None if seconds is None else start + seconds
    next_table = next_snapshot = start
    last_table = start
    while not stop.is_set() and (end is None or time.monotonic() < end):
        station.step(0.1)
        now = time.monotonic()
        if now >= next_snapshot:  # what the fleet status queryable answers
            station.refresh_snapshot()
            next_snapshot = now + SNAPSHOT_S
        if table_period_s > 0 and now >= next_table + table_period_s:
            for line in table_lines(station.vehicles, now - last_table):
                emit(line)
            for v in station.vehicles.values():
                v.period_poses = 0
            last_table = next_table = now
        if save_now is not None and save_now.is_set():
            save_now.clear()
            write_fleet(out_dir, station.summary(), station.vehicles)
    deadline = time.monotonic() + settle_s
    while not station.settled() and time.monotonic() < deadline:
        station.step(0.1)
    while station.step(0.0):  # what already arrived
        pass
    summary = station.summary()
    files = write_fleet(out_dir, summary, station.vehicles)
    return GroundResult(summary, files)
