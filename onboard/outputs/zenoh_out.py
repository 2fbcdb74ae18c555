"""zenoh publishing: the pose every frame, a status every second and the map.

Key expressions, all under `nislam/<vehicle>/` (`[zenoh] vehicle`):

    pose                every frame, JSON: seq (0, 1, ... per publisher),
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
                        map held (map_keyframes, map_points, map_bytes),
                        dropped_poses, dropped_keyframes, errors, uptime_s.
    map/keyframe/<id>   each finished key frame, binary: the encoding of
                        onboard/outputs/mapcodec.py (encoding
                        "application/octet-stream;nislam-keyframe/1").
                        A key the tracker re-uses is published again when
                        it is left (refined, possibly moved): the newest
                        under an id replaces the older one.
    map/**              a queryable: a `get` on it (or on any key below it)
                        is answered with every key frame held, each as one
                        reply under its own map/keyframe/<id> key. Late
                        joiners fetch the map this way.

Session (`session_config`): mode, connect and listen endpoints from the
config, multicast scouting off unless `multicast_scouting`. In peer mode the
session starts without any peer and connects whenever one appears.

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
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from typing import Any, Generic, TypeVar

import zenoh
from scipy.spatial.transform import Rotation

from onboard import NislamError
from onboard.core.messages import HealthReport, KeyframeCloud, TrackResult, TrackState
from onboard.outputs.mapcodec import ENCODING as KEYFRAME_ENCODING
from onboard.outputs.mapcodec import MapKeyframe, encode_keyframe
from onboard.outputs.settings import ZenohConfig

log = logging.getLogger(__name__)

T = TypeVar("T")


def key_prefix(vehicle: str) -> str:
    return f"nislam/{vehicle}"


def session_config(
    cfg: ZenohConfig,
    mode: str | None = None,
    connect: tuple[str, ...] | None = None,
    listen: tuple[str, ...] | None = None,
) -> zenoh.Config:
    """A zenoh.Config from [zenoh], with optional overrides (command-line flags)."""
    conf = zenoh.Config()
    try:
        conf.insert_json5("mode", json.dumps(mode or cfg.mode))
        conf.insert_json5("connect/endpoints", json.dumps(list(cfg.connect if connect is None
                                                                 else connect)))
        conf.insert_json5("listen/endpoints", json.dumps(list(cfg.listen if listen is None
                                                                else listen)))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    except zenoh.ZError as e:
        raise NislamError(f"zenoh configuration refused: {e}") from None
    return conf


def open_session(conf: zenoh.Config) -> zenoh.Session:
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        raise NislamError(f"cannot open the zenoh session: {e}") from None


def tracking_quality(result: TrackResult) -> int:
    """-1 lost, 0 starting, 1-100 tracking (ODOMETRY's convention)."""
    if result.trusted:
        return int(min(100, max(1, result.quality)))
    return -1 if result.state is TrackState.LOST else 0


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def pose_message(result: TrackResult, seq: int) -> dict[str, Any]:
    """The JSON object published on `pose` for one result."""
    trusted = result.trusted and result.p_W_m is not None and result.R_W_C is not None
    q = Rotation.from_matrix(result.R_W_C).as_quat(canonical=True) if trusted else None
    return {
        "seq": seq,
        "t_s": float(result.t_s),
        "state": result.state.value,
        "trusted": trusted,
        "p_W_m": [float(v) for v in result.p_W_m] if trusted else None,
        "q_W_C_xyzw": [float(v) for v in q] if q is not None else None,
        "pose_var": [_num(v) for v in result.pose_var] if trusted else None,
        "quality": tracking_quality(result),
        "psr": _num(result.psr),
        "keyframe_id": int(result.keyframe_id),
        "reset_counter": int(result.reset_counter),
        "lost_reason": result.lost_reason,
    }


class _Worker(Generic[T]):
    """A thread fed through a bounded deque that drops its oldest item.
    `tick()` (optional) runs after every wake-up and returns the seconds until
    it wants to run again."""

    def __init__(self, name: str, handle: Callable[[T], None], maxlen: int,
                 tick: Callable[[], float] | None = None) -> None:
        self._handle = handle
        self._tick = tick
        self._items: deque[T] = deque(maxlen=maxlen)
        self._cond = threading.Condition()
        self._stopping = False
        self.dropped = 0
        self.errors = 0
        self._failing = False
        self._name = name
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def put(self, item: T) -> None:
        with self._cond:
            if len(self._items) == self._items.maxlen:
                self.dropped += 1
            self._items.append(item)
            self._cond.notify()

    def wake(self) -> None:
        """Run `tick()` now rather than when it asked to."""
        with self._cond:
            self._cond.notify()

    def stop(self, timeout_s: float) -> bool:
        """Handle what is queued, then stop; False if the thread is still busy."""
        with self._cond:
            self._stopping = True
            self._cond.notify()
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    def _run(self) -> None:
        wait_s: float | None = 0.0 if self._tick else None
        while True:
            with self._cond:
                if not self._items and not self._stopping:
                    self._cond.wait(wait_s)
                items = list(self._items)
                self._items.clear()
                stopping = self._stopping
            for item in items:
                self._guard(self._handle, item)
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


class ZenohOutput:
    """Publishes results and key frames on zenoh; see the module docstring.
    An `Output`: `publish`, `publish_keyframe`, `close`."""

    def __init__(self, cfg: ZenohConfig, session: zenoh.Session | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.cfg = cfg
        self.prefix = key_prefix(cfg.vehicle)
        self._clock = clock
        self._own_session = session is None
        self.session = open_session(session_config(cfg)) if session is None else session
        try:
            self._declare(cfg, clock)
        except BaseException:
            if self._own_session:
                self.session.close()
            raise

    def _declare(self, cfg: ZenohConfig, clock: Callable[[], float]) -> None:
        s = self.session
        # BLOCK: a congested link holds up our threads, never the loop, and the
        # only poses lost are the ones our own queue drops (counted in status).
        block = zenoh.CongestionControl.BLOCK
        self._pose_pub = s.declare_publisher(
            f"{self.prefix}/pose", encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=block, express=True,
        )
        self._status_pub = s.declare_publisher(
            f"{self.prefix}/status", encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=block,
        )
        self._matched = threading.Event()
        self._matching = self._pose_pub.declare_matching_listener(self._on_matching)
        self._map_lock = threading.Lock()
        self._map: OrderedDict[int, tuple[bytes, int]] = OrderedDict()  # id -> (message, points)
        self._map_bytes = 0
        self._map_points = 0
        self._evicted = 0  # key frames forgotten because of map_max_mb
        self._queryable = s.declare_queryable(f"{self.prefix}/map/**", self._on_query)
        self._start = clock()
        self._seq = 0
        self._counts = {"frames": 0, "frames_tracked": 0, "frames_lost": 0, "keyframes": 0}
        self._period = {"frames": 0, "tracked": 0, "psr_sum": 0.0, "psr_n": 0}
        self._period_start = clock()
        self._last: TrackResult | None = None
        self._health: HealthReport | None = None
        self._next_status = clock()
        self._pose_worker: _Worker[TrackResult] = _Worker(
            "zenoh-pose", self._put_pose, cfg.queue_frames, tick=self._status_tick)
        self._map_worker: _Worker[KeyframeCloud] = _Worker("zenoh-map", self._put_keyframe, 256)
        self._closed = False
        self._pose_worker.start()
        self._map_worker.start()

    # ------------------------------------------------------------- Output API
    def publish(self, result: TrackResult) -> None:
        self._pose_worker.put(result)
        for cloud in result.finished_keyframes:
            self._map_worker.put(cloud)

    def publish_keyframe(self, cloud: KeyframeCloud) -> None:
        self._map_worker.put(cloud)

    def publish_health(self, report: HealthReport) -> None:
        self._health = report  # one attribute store; the pose thread reads it
        if report.changed:
            self._next_status = self._clock()  # publish the change now
            self._pose_worker.wake()

    def close(self, timeout_s: float = 5.0) -> None:
        """Publish what is queued, then undeclare and close the session."""
        if self._closed:
            return
        self._closed = True
        ok = self._map_worker.stop(timeout_s) & self._pose_worker.stop(timeout_s)
        if not ok:
            log.warning("zenoh publisher threads still busy after %.1f s", timeout_s)
        for entity in (self._matching, self._queryable, self._pose_pub, self._status_pub):
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass
        if self._own_session:
            self.session.close()

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
                    "map_bytes": self._map_bytes}
        return {
            **self._counts, **held,
            "poses_published": self._seq,
            "dropped_poses": self._pose_worker.dropped,
            "dropped_keyframes": self._map_worker.dropped,
            "evicted_keyframes": self._evicted,
            "errors": self._pose_worker.errors + self._map_worker.errors,
        }

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
        c["keyframes"] += int(result.new_keyframe)
        if math.isfinite(result.psr):
            p["psr_sum"] += result.psr
            p["psr_n"] += 1
        self._last = result
        msg = pose_message(result, self._seq)
        self._seq += 1
        self._pose_pub.put(json.dumps(msg, allow_nan=False))

    def _status_tick(self) -> float:
        now = self._clock()
        if now < self._next_status:
            return self._next_status - now
        self._next_status = now + self.cfg.status_period_s
        self._status_pub.put(json.dumps(self._status(now), allow_nan=False))
        return self.cfg.status_period_s

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
            "uptime_s": now - self._start,
            "state": state,
            "health_reason": None if health is None else health.reason,
            "quality": 0 if last is None else tracking_quality(last),
            "lost_reason": None if last is None else last.lost_reason,
            "frame_hz": p["frames"] / span,
            "pose_hz": p["tracked"] / span,
            "psr": None if last is None else _num(last.psr),
            "psr_mean": p["psr_sum"] / p["psr_n"] if p["psr_n"] else None,
            "resets": 0 if last is None else int(last.reset_counter),
            **self.stats(),
        }
        self._period = {"frames": 0, "tracked": 0, "psr_sum": 0.0, "psr_n": 0}
        self._period_start = now
        return out

    def _put_keyframe(self, cloud: KeyframeCloud) -> None:
        kf = MapKeyframe.from_cloud(cloud)
        data = encode_keyframe(kf)
        self._store(kf.keyframe_id, data, kf.num_points)
        self.session.put(
            f"{self.prefix}/map/keyframe/{kf.keyframe_id}", data,
            encoding=KEYFRAME_ENCODING, congestion_control=zenoh.CongestionControl.BLOCK,
        )

    def _store(self, keyframe_id: int, data: bytes, points: int) -> None:
        limit = self.cfg.map_max_mb * 1e6
        with self._map_lock:
            old = self._map.pop(keyframe_id, None)
            if old is not None:
                self._map_bytes -= len(old[0])
                self._map_points -= old[1]
            self._map[keyframe_id] = (data, points)
            self._map_bytes += len(data)
            self._map_points += points
            evicted = 0
            while self._map_bytes > limit and len(self._map) > 1:
                _, (d, n) = self._map.popitem(last=False)
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
        for keyframe_id, data in held:
            key = f"{self.prefix}/map/keyframe/{keyframe_id}"
            if wanted.intersects(zenoh.KeyExpr(key)):
                query.reply(key, data, encoding=KEYFRAME_ENCODING)
