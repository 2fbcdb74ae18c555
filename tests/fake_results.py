"""TrackResults and key frames made from literals, for the output tests and
scripts/bench_outputs.py."""

from __future__ import annotations

import dataclasses

import numpy as np

from onboard.core.camera import CameraModel
from onboard.core.messages import KeyframeCloud, RgbdFrame, TrackResult, TrackState

POSE_VAR = np.array([1e-4, 2e-4, 3e-4, 4e-6, 5e-6, 6e-6])


def track_result(
    t_s: float,
    p_W_m: np.ndarray | None = None,
    R_W_C: np.ndarray | None = None,
    *,
    trusted: bool = True,
    state: TrackState | None = None,
    quality: int = 60,
    reset_counter: int = 0,
    keyframe_id: int = 0,
    lost_reason: str | None = None,
    pose_var: np.ndarray = POSE_VAR,
    finished: tuple[KeyframeCloud, ...] = (),
    psr: float = 42.0,
) -> TrackResult:
    if trusted:
        p = np.zeros(3) if p_W_m is None else np.asarray(p_W_m, dtype=np.float64)
        r = np.eye(3) if R_W_C is None else np.asarray(R_W_C, dtype=np.float64)
        var = np.asarray(pose_var, dtype=np.float64)
    else:
        p, r, var, quality, psr = None, None, np.full(6, np.nan), 0, float("nan")
    return TrackResult(
        t_s=t_s,
        state=state or (TrackState.TRACKING if trusted else TrackState.LOST),
        trusted=trusted,
        p_W_m=p,
        R_W_C=r,
        pose_var=var,
        quality=quality,
        psr=psr,
        keyframe_id=keyframe_id,
        new_keyframe=bool(finished),
        reset_counter=reset_counter,
        lost_reason=lost_reason if not trusted else None,
        shift_cells=(0.0, 0.0),
        tz_m=0.0,
        res_m=0.01,
        rotation_residual_rad=np.zeros(3),
        attitude_offset_s=0.0,
        matched_cells=1000,
        finished_keyframes=finished,
    )


def keyframe(keyframe_id: int, shape: tuple[int, int] = (60, 80), seed: int = 0,
             fill: float = 0.6) -> KeyframeCloud:
    """A key frame with random depth in a share `fill` of its cells, random
    colours, some cells without colour (gray used), and a random pose."""
    rng = np.random.default_rng(seed + 1000 * keyframe_id)
    h, w = shape
    depth = rng.uniform(0.3, 4.0, shape).astype(np.float32)
    depth[rng.random(shape) > fill] = 0.0
    bgr = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    bgr[rng.random(shape) < 0.1] = 0
    gray = rng.random(shape)
    angle = rng.uniform(-np.pi, np.pi)
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return KeyframeCloud(keyframe_id, 100.0 + keyframe_id, rng.normal(size=3), R,
                         float(rng.uniform(0.005, 0.03)), depth, gray, bgr)


class ScriptedTracker:
    """A tracker for the service-loop tests: trusted poses moving at 0.1 m/s
    along x, `jump_m` further from frame number `jump_at` or from time
    `jump_at_s` on (the tracker re-found its key in the wrong place)."""

    name = "scripted"

    def __init__(self, jump_at: int | None = None, jump_m: float = 0.49,
                 jump_at_s: float | None = None) -> None:
        self.k = 0
        self.jump_at, self.jump_m, self.jump_at_s = jump_at, jump_m, jump_at_s

    def track(self, frame, attitude) -> TrackResult:
        self.k += 1
        x = 0.1 * (frame.t_s - 100.0)
        if ((self.jump_at is not None and self.k >= self.jump_at)
                or (self.jump_at_s is not None and frame.t_s >= self.jump_at_s)):
            x += self.jump_m
        return dataclasses.replace(
            track_result(frame.t_s, np.array([x, 0.0, 1.0]), quality=80, psr=20.0,
                         keyframe_id=1, pose_var=np.full(6, 1e-4)),
            matched_cells=100)

    def finish(self):
        return None


class NullRunner:
    """The driver runner of a Sources built from fakes: nothing to start or stop."""

    stop_times_s: dict[str, float] = {}

    def start(self) -> None:
        pass

    def stop(self, timeout_s: float = 5.0) -> bool:
        return True


class FakeCamera:
    """A CameraSource of `n` blank 64x48 frames at 30 Hz from t = 100 s,
    handed out one per take(), then exhausted."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.next = 0
        self.model = CameraModel(100.0, 100.0, 32.0, 24.0, 64, 48, 1000.0)

    def wait_camera(self, timeout_s: float) -> CameraModel:
        return self.model

    def take(self, after_seq: int = 0, timeout_s: float = 0.0):
        if self.next >= self.n:
            return None
        self.next += 1
        t = 100.0 + self.next / 30.0
        return self.next, RgbdFrame(t, np.zeros((48, 64, 3), np.uint8), np.ones((48, 64), np.float32))

    @property
    def exhausted(self) -> bool:
        return self.next >= self.n
