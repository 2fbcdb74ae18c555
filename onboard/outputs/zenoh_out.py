"""zenoh publishing: the pose every frame, a status every second and the map.

Key expressions, all under `nislam/<vehicle>/` (`[zenoh] vehicle`):

    pose                every frame, JSON: seq (0, 1, ... per publisher), boot,
                        sent_unix_s (wall clock at the put: latency),
                        t_s (capture time), state ("initializing",
                        "tracking", "lost"), trusted, p_W_m [x, y, z],
                        q_W_C_xyzw, pose_var (6 variances: x, y, z m^2, roll,
                        pitch, yaw rad^2), quality, psr, keyframe_id,
                        reset_counter, lost_reason; the pose fields are null
                        when the frame is not trusted. W is the tracker's
                        world, C the camera optical frame (docs/frames.md).
    status              every `status_period_s` (and at once when the loop's
                        health changes), JSON: state (the onboard loop's
                        health: "starting", "tracking", "degraded", "lost",
                        with health_reason; without a loop, the last
                        result's state), quality (-1 lost,
                        0 starting, 1-100), frame_hz and pose_hz over the
                        period, psr (last) and psr_mean, counters (frames,
                        frames_tracked, frames_lost, keyframes, resets), the
                        map held (map_keyframes, map_points, map_bytes,
                        map_digest: mapcodec.map_digest of the ids and
                        CRC-32s held), keyframes_published (distinct ids),
                        bytes_put by kind, dropped_poses, dropped_keyframes,
                        errors, uptime_s, trackers_used and trackers_left_out
                        (the fused tracker: names; name -> why), boot (random per process: a
                        restarted vehicle keeps its id, its boot changes).
                        A last status goes out at close.
    alive               a liveliness token while the session is up.
    map/keyframe/<id>   each finished key frame, binary: the encoding of
                        onboard/outputs/mapcodec.py (encoding
                        "application/octet-stream;nislam-keyframe/1").
                        A key the tracker re-uses is published again when
                        it is left, one a loop closure moved at once at its
                        new pose: the newest under an id replaces the older.
    map/**              a queryable: a `get` on it (or on any key below it)
                        is answered with every key frame held, each as one
                        reply under its own map/keyframe/<id> key. Late
                        joiners fetch the map this way. Key-frame puts and
                        replies carry the publisher's boot as attachment.

Session (onboard/outputs/zenoh_session.py): mode, connect and listen
endpoints and TLS from the config, scouting off unless `multicast_scouting`.
A peer starts without any peer and connects whenever one appears; a client
(a fleet vehicle of a router, docs/fleet.md) opens on a helper thread, since
zenoh's open waits for the router: until then results are counted and key
frames held, nothing is put. Both reconnect by themselves when the router
comes back; key frames put meanwhile are lost on the wire, and the status's
map_digest tells a ground station to fetch the map again.

Priorities (`pose_priority` > `status_priority` > `map_priority`): a busy
link delays key frames, not poses. `map_rate_kb_s` limits the average rate of
key-frame puts (a one-second allowance), on the map thread only.

Threads. `publish()` appends the result to a bounded queue (the oldest is
dropped when full) and returns; the `zenoh-pose` thread encodes and puts poses
and the status, the `zenoh-map` thread encodes and puts key frames, so a big
key frame never delays a pose. Puts use congestion control BLOCK: a slow link
holds up these threads, never the loop, and the only poses lost are those our
queue drops (`dropped_poses` in the status);
zenoh's own threads answer queries from the key frames held. The tracking
loop never encodes, copies a cloud or touches the network.
"""

from __future__ import annotations

import json
import logging
import math
import secrets
import threading
import time
import zlib
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import zenoh

from onboard.core.messages import HealthReport, KeyframeCloud, TrackResult
from onboard.outputs.mapcodec import ENCODING as KEYFRAME_ENCODING
from onboard.outputs.mapcodec import KeyframeMove, MapKeyframe, encode_keyframe, map_digest
from onboard.outputs.settings import ZenohConfig
from onboard.outputs.wake import Wake
from onboard.outputs.zenoh_link import ZenohLink
from onboard.outputs.zenoh_messages import RateLimit, finite_or_none, pose_message, tracking_quality
from onboard.outputs.zenoh_session import (
    Worker,
    key_prefix,
    open_session,
    priority,
    session_config,
)

__all__ = ["ZenohOutput", "key_prefix", "open_session", "pose_message", "session_config"]

log = logging.getLogger(__name__)


class _Entities:
    """What is declared on an open session, set once (atomically) when it is."""

    def __init__(self, out: ZenohOutput, s: zenoh.Session) -> None:
        cfg, prefix = out.cfg, out.prefix
        # BLOCK: a congested link holds up our threads, never the loop, and the
        # only poses lost are the ones our own queue drops (counted in status).
        block = zenoh.CongestionControl.BLOCK
        self.session = s
        self.pose = s.declare_publisher(
            f"{prefix}/pose", encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=block, express=True, priority=priority(cfg.pose_priority))
        self.status = s.declare_publisher(
            f"{prefix}/status", encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=block, priority=priority(cfg.status_priority))
        self.matching = self.pose.declare_matching_listener(out._on_matching)
        self.queryable = s.declare_queryable(f"{prefix}/map/**", out._on_query)
        self.alive = s.liveliness().declare_token(f"{prefix}/alive")

    def undeclare(self) -> None:
        for entity in (self.alive, self.matching, self.queryable, self.pose, self.status):
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass


class ZenohOutput:
    """Publishes results and key frames on zenoh; see the module docstring.
    An `Output`: `publish`, `publish_keyframe`, `close`."""

    def __init__(self, cfg: ZenohConfig, session: zenoh.Session | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.cfg = cfg
        self.prefix = key_prefix(cfg.vehicle)
        self.boot = secrets.token_hex(4)  # this process's run: a restart shows as a new boot
        self._clock = clock
        self._own_session = session is None
        self._entities: _Entities | None = None
        self._connected = threading.Event()  # the session is open, entities declared
        self._closing = threading.Event()
        self._init_state(cfg, clock)
        if session is None and cfg.mode == "client":
            # A client's open waits for its router: never in the loop's way.
            conf = session_config(cfg)
            self._opener = threading.Thread(target=self._open_later, args=(conf,),
                                            name="zenoh-open", daemon=True)
            self._opener.start()
        else:
            self._attach(open_session(session_config(cfg)) if session is None else session)
        self._pose_worker.start()
        self._map_worker.start()

    @property
    def session(self) -> zenoh.Session:
        if self._entities is None:
            raise RuntimeError("the zenoh session is not open yet")
        return self._entities.session

    def _attach(self, s: zenoh.Session) -> None:
        try:
            self._entities = _Entities(self, s)
        except BaseException:
            if self._own_session:
                s.close()
            raise
        self._connected.set()

    def wait_connected(self, timeout_s: float) -> bool:
        """True once the session is open (a client: its router answered)."""
        return self._connected.wait(timeout_s)

    def _open_later(self, conf: zenoh.Config) -> None:
        log.info("zenoh: connecting to %s (client mode: waiting for the router)",
                 ", ".join(self.cfg.connect) or "nothing")
        try:
            s = zenoh.open(conf)
        except zenoh.ZError as e:
            log.error("zenoh: cannot open the session: %s (nothing is published)", e)
            return
        if self._closing.is_set():
            s.close()
            return
        self._attach(s)
        log.info("zenoh: session open")

    def _init_state(self, cfg: ZenohConfig, clock: Callable[[], float]) -> None:
        self._matched = threading.Event()
        self._map_lock = threading.Lock()
        self._map: OrderedDict[int, tuple[bytes, int]] = OrderedDict()  # id -> (message, points)
        self._crc: dict[int, int] = {}  # id -> CRC-32 of its message (map_digest)
        self._ids: set[int] = set()  # every key-frame id ever handed over
        self._map_bytes = 0
        self._map_points = 0
        self._evicted = 0  # key frames forgotten because of map_max_mb
        self._rate = RateLimit(cfg.map_rate_kb_s * 1e3)
        self._bytes = {"pose": 0, "status": 0, "map": 0}  # payload bytes put
        self._start = clock()
        self._seq = 0
        self._counts = {"frames": 0, "frames_tracked": 0, "frames_lost": 0, "keyframes": 0}
        self._period = {"frames": 0, "tracked": 0, "psr_sum": 0.0, "psr_n": 0}
        self._period_start = clock()
        self._last: TrackResult | None = None
        # The link to the router or peers of `connect`: one warning when it
        # goes, one line when it is back (onboard/outputs/zenoh_link.py).
        self.link = ZenohLink(cfg, clock)
        self.device_state = self.link.state if self.link.watched else None
        self._health: HealthReport | None = None
        self._next_status = clock()
        self._pose_worker: Worker[TrackResult] = Worker(
            "zenoh-pose", self._put_pose, cfg.queue_frames, tick=self._tick)
        self._map_worker: Worker[KeyframeCloud | KeyframeMove] = Worker(
            "zenoh-map", self._put_keyframe, 256)
        self._closed = False
        # Set by the service (onboard.app.latency.attach_timing): the loop's
        # latency, TIMESYNC and delay advice in the status; encode-and-put times.
        self.status_extra: Callable[[], dict[str, Any]] | None = None
        self.on_stage: Callable[[str, float], None] | None = None

    # ------------------------------------------------------------- Output API
    def publish(self, result: TrackResult) -> None:
        self._pose_worker.put(result)
        for cloud in result.finished_keyframes:
            self._map_worker.put(cloud)
        for kf_id, p_W, R_W_C in result.moved_keyframes:  # a loop closure moved them
            self._map_worker.put(KeyframeMove(kf_id, p_W, R_W_C))

    def publish_keyframe(self, cloud: KeyframeCloud) -> None:
        self._map_worker.put(cloud)

    def wakeups(self) -> tuple[Wake, ...]:
        """The publisher threads' wake-ups (onboard/outputs/wake.py)."""
        return (self._pose_worker.wakeup, self._map_worker.wakeup)

    def publish_health(self, report: HealthReport) -> None:
        self._health = report  # one attribute store; the pose thread reads it
        if report.changed:
            self._next_status = self._clock()  # publish the change now
            self._pose_worker.wake()

    def close(self, timeout_s: float = 5.0) -> None:
        """Publish what is queued (the map rate limit no longer applies) and a
        last status, then undeclare and close the session."""
        if self._closed:
            return
        self._closed = True
        self._closing.set()
        ok = self._map_worker.stop(timeout_s) & self._pose_worker.stop(timeout_s)
        if not ok:
            log.warning("zenoh publisher threads still busy after %.1f s", timeout_s)
        ent = self._entities
        if ent is None:
            return
        try:  # the final map digest: a ground station can tell it holds every key frame
            self._put_status(self._clock())
        except zenoh.ZError as e:
            log.debug("last status not sent: %s", e)
        ent.undeclare()
        if self._own_session:
            ent.session.close()

    def __enter__(self) -> ZenohOutput:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def wait_for_subscribers(self, timeout_s: float) -> bool:
        """True once a subscriber of `pose` is connected (tests, tools)."""
        return self._matched.wait(timeout_s)

    def stats(self) -> dict[str, Any]:
        with self._map_lock:
            held = {"map_keyframes": len(self._map), "map_points": self._map_points,
                    "map_bytes": self._map_bytes, "map_digest": map_digest(self._crc),
                    "keyframes_published": len(self._ids)}
        return {
            **self._counts, **held,
            "poses_published": self._seq,
            "dropped_poses": self._pose_worker.dropped,
            "dropped_keyframes": self._map_worker.dropped,
            "evicted_keyframes": self._evicted,
            "errors": self._pose_worker.errors + self._map_worker.errors,
            "bytes_put": dict(self._bytes),
            "connected": self._entities is not None,
        }

    def run_stats(self) -> dict[str, Any]:
        """`stats()` and the CRC-32 of the message of every key frame held, by
        id (run.json: a ground station's map can be checked against it)."""
        with self._map_lock:
            crcs = {str(k): self._crc[k] for k in sorted(self._crc)}
        return {**self.stats(), "keyframe_crc32": crcs}

    # ------------------------------------------------------------- threads
    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        if status.matching:
            self._matched.set()
        else:
            self._matched.clear()

    def _put_pose(self, result: TrackResult) -> None:
        c, p = self._counts, self._period
        c["frames"] += 1
        p["frames"] += 1
        if result.trusted:
            c["frames_tracked"] += 1
            p["tracked"] += 1
        else:
            c["frames_lost"] += 1
        c["keyframes"] += result.keyframes_added
        if math.isfinite(result.psr):
            p["psr_sum"] += result.psr
            p["psr_n"] += 1
        self._last = result
        ent = self._entities
        if ent is None:
            return  # not connected yet (a client waiting for its router)
        t0 = time.perf_counter()
        msg = pose_message(result, self._seq)
        msg["boot"] = self.boot
        msg["sent_unix_s"] = time.time()  # latency on the ground (clocks synchronised)
        data = json.dumps(msg, allow_nan=False)
        self._seq += 1
        ent.pose.put(data)
        self._bytes["pose"] += len(data)
        if self.on_stage is not None:
            self.on_stage("zenoh_pose_encode_put", (time.perf_counter() - t0) * 1e3)

    def _tick(self) -> float:
        ent = self._entities
        return min(self.link.poll(None if ent is None else ent.session), self._status_tick())

    def _status_tick(self) -> float:
        now = self._clock()
        if now < self._next_status:
            return self._next_status - now
        self._next_status = now + self.cfg.status_period_s
        self._put_status(now)
        return self.cfg.status_period_s

    def _put_status(self, now: float) -> None:
        ent = self._entities
        if ent is None:
            return
        t0 = time.perf_counter()
        data = json.dumps(self._status(now), allow_nan=False)
        ent.status.put(data)
        if self.on_stage is not None:
            self.on_stage("zenoh_status_encode_put", (time.perf_counter() - t0) * 1e3)
        self._bytes["status"] += len(data)

    def _status(self, now: float) -> dict[str, Any]:
        last, p, health = self._last, self._period, self._health
        span = max(now - self._period_start, 1e-9)
        if health is not None:
            state = health.state.value
        else:
            state = "starting" if last is None else last.state.value
        out = {
            "t_s": now,
            "vehicle": self.cfg.vehicle,
            "boot": self.boot,
            "uptime_s": now - self._start,
            "state": state,
            "health_reason": None if health is None else health.reason,
            "devices": [] if health is None else list(health.devices),  # each driver's state
            "quality": 0 if last is None else tracking_quality(last),
            "lost_reason": None if last is None else last.lost_reason,
            "frame_hz": p["frames"] / span,
            "pose_hz": p["tracked"] / span,
            "psr": None if last is None else finite_or_none(last.psr),
            "psr_mean": p["psr_sum"] / p["psr_n"] if p["psr_n"] else None,
            "resets": 0 if last is None else int(last.reset_counter),
            # the fused tracker: which trackers the pose used, why others were left out
            "trackers_used": None if last is None else list(last.contributors),
            "trackers_left_out": None if last is None else dict(last.left_out),
            **self.stats(),
            **(self.status_extra() if self.status_extra is not None else {}),
        }
        self._period = {"frames": 0, "tracked": 0, "psr_sum": 0.0, "psr_n": 0}
        self._period_start = now
        return out

    def _put_keyframe(self, item: KeyframeCloud | KeyframeMove) -> None:
        t0 = time.perf_counter()
        if isinstance(item, KeyframeMove):
            kf = self._moved(item)
            if kf is None:
                return
        else:
            kf = MapKeyframe.from_cloud(item)
        data = encode_keyframe(kf)
        if self.on_stage is not None:
            self.on_stage("zenoh_map_encode", (time.perf_counter() - t0) * 1e3)
        self._store(kf.keyframe_id, data, kf.num_points)
        delay_s = self._rate.delay_s(len(data), self._clock())
        if delay_s > 0:  # the map rate limit; ends at close (flush what is left)
            self._closing.wait(delay_s)
        ent = self._entities
        if ent is None:
            return  # held for the queryable: a ground station fetches it once connected
        ent.session.put(
            f"{self.prefix}/map/keyframe/{kf.keyframe_id}", data,
            encoding=KEYFRAME_ENCODING, congestion_control=zenoh.CongestionControl.BLOCK,
            priority=priority(self.cfg.map_priority), attachment=self.boot,
        )
        self._bytes["map"] += len(data)

    def _moved(self, m: KeyframeMove) -> MapKeyframe | None:
        """A held key frame at its new pose; None if never held or evicted."""
        with self._map_lock:
            held = self._map.get(m.keyframe_id)
        return None if held is None else m.applied(held[0])

    def _store(self, keyframe_id: int, data: bytes, points: int) -> None:
        limit = self.cfg.map_max_mb * 1e6
        with self._map_lock:
            old = self._map.pop(keyframe_id, None)
            if old is not None:
                self._map_bytes -= len(old[0])
                self._map_points -= old[1]
            self._map[keyframe_id] = (data, points)
            self._crc[keyframe_id] = zlib.crc32(data)
            self._ids.add(keyframe_id)
            self._map_bytes += len(data)
            self._map_points += points
            evicted = 0
            while self._map_bytes > limit and len(self._map) > 1:
                k, (d, n) = self._map.popitem(last=False)
                del self._crc[k]
                self._map_bytes -= len(d)
                self._map_points -= n
                evicted += 1
        if evicted:
            # Once at warning level: from then on the cap is the normal state.
            level = logging.DEBUG if self._evicted else logging.WARNING
            log.log(level, "map above %.0f MB: forgot the %d oldest key frames for late joiners "
                    "(further evictions are logged at debug level)", self.cfg.map_max_mb, evicted)
            self._evicted += evicted

    def _on_query(self, query: zenoh.Query) -> None:
        """Every key frame held whose key matches the query, one reply each."""
        with self._map_lock:
            held = [(k, d) for k, (d, _n) in self._map.items()]
        wanted = query.key_expr
        for keyframe_id, data in held:  # (a reply goes at the query's priority)
            key = f"{self.prefix}/map/keyframe/{keyframe_id}"
            if wanted.intersects(zenoh.KeyExpr(key)):
                query.reply(key, data, encoding=KEYFRAME_ENCODING, attachment=self.boot)
