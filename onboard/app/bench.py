"""Time the tracker alone on frames already decoded and undistorted in memory.

Only `tracker.track()` is inside the timer, and everything it does counts
(projection, correlation, depth translation, calibration, key-frame work):
that is the per-frame budget the onboard loop has to fit in.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from onboard.app.config import Config
from onboard.fusion.registry import make_tracker
from sim_replay.attitude import AttitudeErrorModel, attitude_for_replay
from sim_replay.tum import open_sequence

log = logging.getLogger(__name__)


def pin_one_core() -> None:
    """Keep OpenCV on the calling thread. The tracker must fit one core of the
    companion computer (drivers and outputs share the others), so timings
    measured with OpenCV's thread pool would promise speed the drone lacks.
    scipy.fft is already called with workers=1 in onboard.nislam.correlation."""
    cv2.setNumThreads(1)


def frame_time_stats(frame_ms: list[float] | np.ndarray) -> dict[str, float | None]:
    """Median, p95, max and mean milliseconds per frame and the rate the
    median allows (Hz); all None when there are no samples."""
    ms = np.asarray(frame_ms, dtype=np.float64)
    if len(ms) == 0:
        return dict.fromkeys(
            ("frame_ms_median", "frame_ms_p95", "frame_ms_max", "frame_ms_mean", "hz")
        )
    median = float(np.median(ms))
    return {
        "frame_ms_median": median,
        "frame_ms_p95": float(np.percentile(ms, 95)),
        "frame_ms_max": float(ms.max()),
        "frame_ms_mean": float(ms.mean()),
        "hz": 1000.0 / median if median > 0 else None,
    }


def attitude_error_model(cfg: Config) -> AttitudeErrorModel:
    a = cfg.attitude
    return AttitudeErrorModel(a.noise_deg, a.bias_deg_per_sqrt_s, a.offset_ms, a.seed)


def bench(
    seq_dir: Path | str, cfg: Config, max_frames: int | None = None, repeat: int = 1
) -> dict[str, Any]:
    """Per-frame `track()` times over the sequence, `repeat` passes with a
    fresh tracker each (so every pass includes the same key-frame work)."""
    pin_one_core()
    seq = open_sequence(seq_dir, cfg.replay.assoc_max_dt_s, cfg.replay.undistort)
    attitude, _label = attitude_for_replay(
        seq, attitude_error_model(cfg), cfg.replay.gt_max_gap_s
    )
    log.info("decoding %d frames into memory", len(seq) if max_frames is None else max_frames)
    frames = seq.load_all(max_frames)
    frame_ms: list[float] = []
    # by kind: a frame that starts a key or re-uses a kept one does more work
    kind_ms: dict[str, list[float]] = {"keyframe": [], "reused": [], "plain": []}
    parts_ms: dict[str, list[float]] = {}  # the fused tracker's parts (last_part_ms)
    for _ in range(repeat):
        tracker = make_tracker(cfg.tracker.name, seq.intrinsics, cfg)
        for frame in frames:
            t0 = time.perf_counter()
            result = tracker.track(frame, attitude)
            dt_ms = (time.perf_counter() - t0) * 1e3
            frame_ms.append(dt_ms)
            kind = ("keyframe" if result.new_keyframe
                    else "reused" if result.keyframe_reused else "plain")
            kind_ms[kind].append(dt_ms)
            for part, ms in getattr(tracker, "last_part_ms", {}).items():
                parts_ms.setdefault(part, []).append(ms)
    by_kind: dict[str, Any] = {}
    for kind, ms in kind_ms.items():
        by_kind[f"{kind}_frames"] = len(ms) // repeat
        by_kind[f"{kind}_frames_ms_median"] = float(np.median(ms)) if ms else None
    return {
        "sequence": str(Path(seq_dir).resolve()),
        "tracker": cfg.tracker.name,
        "frames": len(frames),
        "repeat": repeat,
        **frame_time_stats(frame_ms),
        **by_kind,
        "parts_ms_median": {part: float(np.median(ms)) for part, ms in parts_ms.items()},
    }
