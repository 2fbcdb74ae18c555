"""`nislam listen` as a function: the ground side of the zenoh outputs.

Subscribes to one vehicle's pose, status and key frames, fetches the map it
already has through its queryable, keeps the map up to date, prints what
arrives, and writes the map as PLY when stopped. When a status says the
vehicle holds more key frames than we do (we joined late, or the link
dropped some), the map is fetched again (at most every `REFETCH_S`).

zenoh delivers on its own threads; they only decode and queue. One thread
(the caller's) prints and owns the map, so nothing here needs a lock.
"""

from __future__ import annotations

import json
import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from onboard.outputs.mapcodec import MapCodecError, MapKeyframe, decode_keyframe
from onboard.outputs.ply import write_ply
from onboard.outputs.settings import ZenohConfig
from onboard.outputs.zenoh_session import key_prefix, open_waiting, session_config

log = logging.getLogger(__name__)

REFETCH_S = 2.0


@dataclass
class ListenResult:
    poses: int
    statuses: int
    keyframes: int  # held at the end
    points: int
    out: Path | None


class MapListener:
    """One vehicle's topics on an open session; events go to `events`."""

    def __init__(self, session: zenoh.Session, vehicle: str) -> None:
        self.session = session
        self.prefix = key_prefix(vehicle)
        self.events: queue.Queue[tuple[str, Any]] = queue.Queue()
        self.keyframes: dict[int, MapKeyframe] = {}
        self._subs = [
            session.declare_subscriber(f"{self.prefix}/pose", self._on_json("pose")),
            session.declare_subscriber(f"{self.prefix}/status", self._on_json("status")),
            session.declare_subscriber(f"{self.prefix}/map/keyframe/*", self._on_keyframe),
        ]

    def close(self) -> None:
        for sub in self._subs:
            try:
                sub.undeclare()
            except zenoh.ZError:
                pass

    def _on_json(self, kind: str) -> Callable[[zenoh.Sample], None]:
        def callback(sample: zenoh.Sample) -> None:
            try:
                self.events.put((kind, json.loads(sample.payload.to_bytes())))
            except ValueError as e:
                log.warning("bad %s message on %s: %s", kind, sample.key_expr, e)
        return callback

    def _on_keyframe(self, sample: zenoh.Sample) -> None:
        try:
            self.events.put(("keyframe", decode_keyframe(sample.payload.to_bytes())))
        except MapCodecError as e:
            log.warning("bad key frame on %s: %s", sample.key_expr, e)

    def fetch_map(self, timeout_s: float) -> list[MapKeyframe]:
        """Every key frame the vehicle holds, through its queryable."""
        out = []
        for reply in self.session.get(f"{self.prefix}/map/**", timeout=timeout_s):
            if reply.ok is None:
                log.warning("map query: error reply: %s", reply.err.payload.to_string())
                continue
            try:
                out.append(decode_keyframe(reply.ok.payload.to_bytes()))
            except MapCodecError as e:
                log.warning("bad key frame from %s: %s", reply.ok.key_expr, e)
        return out

    def add(self, kf: MapKeyframe) -> bool:
        """Hold `kf`; True if its id is new."""
        new = kf.keyframe_id not in self.keyframes
        self.keyframes[kf.keyframe_id] = kf
        return new

    @property
    def num_points(self) -> int:
        return sum(kf.num_points for kf in self.keyframes.values())

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """The whole map, key frames in id order."""
        parts = [self.keyframes[k].points() for k in sorted(self.keyframes)]
        if not parts:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


class _Printer:
    """Human lines (poses at most `pose_hz`) or, with `json_lines`, every event."""

    def __init__(self, emit: Callable[[str], None], json_lines: bool, pose_hz: float) -> None:
        self.emit = emit
        self.json = json_lines
        self.pose_period = 1.0 / pose_hz if pose_hz > 0 else math.inf
        self._next_pose = 0.0

    def event(self, kind: str, fields: dict[str, Any], text: Callable[[], str]) -> None:
        if self.json:
            self.emit(json.dumps({"type": kind, **fields}, allow_nan=False))
            return
        if kind == "pose":
            now = time.monotonic()
            if now < self._next_pose:
                return
            self._next_pose = now + self.pose_period
        self.emit(text())


def _pose_text(m: dict[str, Any]) -> str:
    if not m.get("trusted"):
        return f"pose   t {m['t_s']:.3f}  {m['state']:<12} ({m.get('lost_reason') or 'no pose'})"
    x, y, z = m["p_W_m"]
    return (f"pose   t {m['t_s']:.3f}  {m['state']:<12} p_W [{x:+8.3f} {y:+8.3f} {z:+8.3f}] m  "
            f"q {m['quality']:3d}  key {m['keyframe_id']}  resets {m['reset_counter']}")


def _status_text(m: dict[str, Any]) -> str:
    psr = "n/a" if m.get("psr_mean") is None else f"{m['psr_mean']:.1f}"
    return (f"status {m['state']}, quality {m['quality']}, {m['frame_hz']:.1f} Hz frames, "
            f"{m['pose_hz']:.1f} Hz poses, psr {psr}, frames {m['frames']} "
            f"(lost {m['frames_lost']}), key frames {m['keyframes']}, resets {m['resets']}, "
            f"map {m['map_keyframes']} key frames / {m['map_points']} points, "
            f"dropped {m['dropped_poses']}")


def listen(
    cfg: ZenohConfig,
    stop: threading.Event,
    out: Path | None = None,
    emit: Callable[[str], None] = print,
    json_lines: bool = False,
    pose_hz: float = 2.0,
    fetch_timeout_s: float = 20.0,
) -> ListenResult:
    """Listen to `cfg.vehicle` until `stop` is set; write the map to `out`."""
    printer = _Printer(emit, json_lines, pose_hz)
    poses = statuses = 0
    session = open_waiting(session_config(cfg), stop, on_wait=lambda: log.warning(
        "waiting for %s (a client waits for its router)", ", ".join(cfg.connect) or "a peer"))
    if session is None:  # stopped before the session opened
        return ListenResult(0, 0, 0, 0, None)
    with session:
        listener = MapListener(session, cfg.vehicle)
        try:
            printer.event("ready", {"vehicle": cfg.vehicle},
                          lambda: f"listening to {listener.prefix}/** (Ctrl-C to stop)")
            last_fetch = -math.inf

            def fetch() -> None:
                nonlocal last_fetch
                last_fetch = time.monotonic()
                got = listener.fetch_map(fetch_timeout_s)
                new = sum(listener.add(kf) for kf in got)
                printer.event(
                    "map", {"fetched": len(got), "new": new, "keyframes": len(listener.keyframes),
                            "points": listener.num_points},
                    lambda: f"map    fetched {len(got)} key frames ({new} new): "
                            f"{len(listener.keyframes)} key frames, {listener.num_points} points")

            fetch()
            while not stop.is_set():
                try:
                    kind, item = listener.events.get(timeout=0.2)
                except queue.Empty:
                    continue
                if kind == "pose":
                    poses += 1
                    printer.event("pose", item, lambda: _pose_text(item))
                elif kind == "status":
                    statuses += 1
                    printer.event("status", item, lambda: _status_text(item))
                    behind = item.get("map_keyframes", 0) > len(listener.keyframes)
                    if behind and time.monotonic() - last_fetch > REFETCH_S:
                        fetch()
                elif kind == "keyframe":
                    listener.add(item)
                    printer.event(
                        "keyframe", {"keyframe_id": item.keyframe_id, "points": item.num_points,
                                     "t_s": item.t_s, "p_W_m": item.p_W_m.tolist(),
                                     "R_W_C": item.R_W_C.tolist(), "res_m": item.res_m,
                                     "keyframes": len(listener.keyframes)},
                        lambda: f"map    + key frame {item.keyframe_id} ({item.num_points} "
                                f"points): {len(listener.keyframes)} key frames")
        finally:
            listener.close()
    n_points = listener.num_points
    if out is not None:
        xyz, rgb = listener.points()
        write_ply(out, xyz, rgb)
        printer.event("saved", {"path": str(out), "keyframes": len(listener.keyframes),
                                "points": n_points},
                      lambda: f"saved  {len(listener.keyframes)} key frames, {n_points} points "
                              f"to {out}")
    return ListenResult(poses, statuses, len(listener.keyframes), n_points, out)
