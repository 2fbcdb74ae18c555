"""The closed loop's renderer in its own process (`[sim_follow]
render_process = true`): the simulated camera is the world's, not the
companion's, so it should not take the tracker's interpreter lock. On this
project's loaded 2-core test machine the extra process cost more CPU than
the lock did (640x480 circle: 10-14 Hz with it, 16-17 Hz without, load ~9),
so it is off by default; on a machine with a core to spare it keeps the
renderer's Python from delaying the tracker.

`RenderProcess` starts a worker (spawn: no fork of a threaded process) that
builds the scene's renderer and sensor models (textures from the cache),
then answers requests over a pipe: the camera pose and the frame index in,
colour and depth out through two shared-memory slots (the caller copies the
frame out before it asks for the one after next). The worker ends when the
pipe closes, so it never outlives the service.
"""

from __future__ import annotations

import hashlib
import logging
import multiprocessing as mp
import os
import time
from dataclasses import dataclass
from multiprocessing import shared_memory
from pathlib import Path
from typing import Any

import numpy as np

from sim_replay.render import Renderer

log = logging.getLogger(__name__)

START_TIMEOUT_S = 60.0


@dataclass(frozen=True)
class RenderSpec:
    """Everything the worker needs to build the same renderer."""

    scene: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    seed: int
    texture_cache: str | None
    sigma_m_per_m2: float
    min_range_m: float
    max_range_m: float
    edge_rel: float
    edge_width_px: int
    dropout: float
    pixel_noise_dn: float


def _texture_key(renderer: Renderer) -> str:
    """What the textures depend on: the scene, seed, texel size and the code
    that makes them (a changed generator never loads stale textures)."""
    h = hashlib.sha1()
    for mod in ("textures.py", "scene.py", "render.py"):
        h.update((Path(__file__).parent / mod).read_bytes())
    h.update(f"{renderer.scene.name}|{renderer.seed}|{renderer.texel_m!r}".encode())
    return f"{renderer.scene.name}-{h.hexdigest()[:16]}"


def prepare_textures(renderer: Renderer, cache_dir: Path | None) -> None:
    """Build every surface's texture now, or load them from `cache_dir`
    (the room's take ~5 s to build and ~110 MB to keep: a restarted service
    is back within a second or two instead)."""
    n = len(renderer.scene.surfaces)
    path = None if cache_dir is None else cache_dir / f"textures-{_texture_key(renderer)}.npz"
    if path is not None and path.is_file():
        try:
            with np.load(path) as z:
                levels: dict[int, list[np.ndarray]] = {}
                for name in z.files:
                    i, k = (int(v) for v in name[1:].split("_"))
                    levels.setdefault(i, []).append((k, z[name]))
            renderer.adopt_textures({i: [a for _, a in sorted(v, key=lambda x: x[0])]
                                     for i, v in levels.items()})
            if len(levels) == n:
                return
        except (OSError, ValueError, KeyError) as e:
            log.warning("ignoring the texture cache %s: %s", path, e)
    for i in range(n):
        renderer.texture(i)
    if path is None:
        return
    tmp = path.with_name(path.name + ".tmp.npz")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(tmp, **{f"s{i}_{k}": a for i, lv in renderer.built_textures().items()
                         for k, a in enumerate(lv)})
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        log.warning("cannot keep the textures in %s: %s", path, e.strerror or e)


def _buffers(spec: RenderSpec, shm: list[shared_memory.SharedMemory]
             ) -> list[tuple[np.ndarray, np.ndarray]]:
    h, w = spec.height, spec.width
    out = []
    for m in shm:
        bgr = np.ndarray((h, w, 3), np.uint8, m.buf, 0)
        depth = np.ndarray((h, w), np.float32, m.buf, h * w * 3)
        out.append((bgr, depth))
    return out


def _worker(spec: RenderSpec, names: list[str], conn: Any) -> None:
    import cv2

    from onboard.core.camera import CameraIntrinsics
    from sim_replay.scene import make_scene
    from sim_replay.sensors import ColourNoise, DepthSensorModel, measure_depth

    cv2.setNumThreads(1)
    shm = [shared_memory.SharedMemory(name=n) for n in names]
    try:
        slots = _buffers(spec, shm)
        intr = CameraIntrinsics(spec.fx, spec.fy, spec.cx, spec.cy, spec.width, spec.height)
        renderer = Renderer(make_scene(spec.scene), intr, seed=spec.seed)
        prepare_textures(renderer, Path(spec.texture_cache) if spec.texture_cache else None)
        model = DepthSensorModel(spec.sigma_m_per_m2, spec.min_range_m, spec.max_range_m,
                                 spec.edge_rel, spec.edge_width_px, spec.dropout)
        noise = ColourNoise((spec.height, spec.width), spec.pixel_noise_dn, spec.seed)
        conn.send(("ready",))
        while True:
            try:
                k, slot, R_W_C, p_W = conn.recv()
            except (EOFError, OSError):
                return
            t0 = time.thread_time()
            view = renderer.render(R_W_C, p_W)
            rng = np.random.default_rng([spec.seed, 1, k])
            bgr, depth = slots[slot]
            depth[...] = measure_depth(view.depth_m, model, rng)
            bgr[...] = noise.apply(view.bgr, rng)
            conn.send(("frame", slot, (time.thread_time() - t0) * 1e3))
    finally:
        slots = []  # views into the shared memory go first, or close() refuses
        for m in shm:
            m.close()


class RenderProcess:
    """A worker process rendering frames on request (see the module docstring)."""

    def __init__(self, spec: RenderSpec) -> None:
        self.spec = spec
        size = spec.width * spec.height * 7  # BGR uint8 + float32 depth
        self._shm = [shared_memory.SharedMemory(create=True, size=size) for _ in range(2)]
        self._slots = _buffers(spec, self._shm)
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_worker, args=(spec, [m.name for m in self._shm], child),
                                 name=f"render:{spec.scene}", daemon=True)
        self._proc.start()
        child.close()
        self._next = 0
        if not self._conn.poll(START_TIMEOUT_S):
            self.close()
            raise RuntimeError("the render process did not start")
        msg = self._conn.recv()
        if msg[0] != "ready":
            self.close()
            raise RuntimeError(f"the render process failed to start: {msg}")

    def render(self, k: int, R_W_C: np.ndarray, p_W_m: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, float]:
        """(bgr, depth_m, CPU ms of the worker) of frame `k` at that pose."""
        slot = self._next
        self._next = 1 - slot
        self._conn.send((k, slot, np.asarray(R_W_C), np.asarray(p_W_m)))
        kind, got, ms = self._conn.recv()  # waits without the GIL
        assert kind == "frame" and got == slot
        bgr, depth = self._slots[slot]
        return bgr.copy(), depth.copy(), ms

    def close(self) -> None:
        try:
            self._conn.close()
        except OSError:
            pass
        self._proc.join(5.0)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(2.0)
        self._slots = []  # views into the shared memory go first, or close() refuses
        for m in self._shm:
            m.close()
            try:
                m.unlink()
            except FileNotFoundError:
                pass
