"""Time the tracker alone on frames already decoded and undistorted in memory.

Only `tracker.track()` is inside the tracker's timer, and everything it does
counts (projection, correlation, depth translation, calibration): that is
the time from a frame to its pose. The work a tracker defers until the pose
is out (`finish_frame()`: NI-SLAM's new key and key refinement) is timed
apart (`deferred_ms_*`, stage `tracker_deferred`); the two together are the
per-frame budget the onboard loop has to fit in.

Beside it, each other stage a frame goes through, timed on its own (`stages_ms`):
the source (decoding the recording's files; undistortion, the colour and
depth remaps, when the camera is distorted), and the outputs' encoding on
their threads (the MAVLink feed's sample and ODOMETRY packet, the zenoh pose's
JSON, each finished key frame's map message). `nislam run --out` measures the
same stages in the running service (run.json `stages_ms`, onboard/app/latency.py).
A back end run in slices after each frame (FastORB's local BA,
`backend_step()`) is timed apart too: per slice and per key frame.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from onboard.app.allocator import keep_freed_memory
from onboard.app.config import Config, with_tracker_resolved
from onboard.app.loop_stats import percentiles_ms
from onboard.core.camera import undistort_maps
from onboard.core.messages import TrackResult
from onboard.fusion.registry import make_tracker
from sim_replay.attitude import AttitudeErrorModel, AttitudeSeries, attitude_for_replay
from sim_replay.tum import Sequence, open_sequence

log = logging.getLogger(__name__)


def pin_one_core() -> None:
    """Keep OpenCV on the calling thread. The tracker must fit one core of the
    companion computer (drivers and outputs share the others), so timings
    measured with OpenCV's thread pool would promise speed the drone lacks.
    NI-SLAM's correlation (onboard.nislam.correlation) is OpenCV's DFT too."""
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


def replay_attitude(seq: Sequence, cfg: Config) -> tuple[AttitudeSeries, str]:
    """The attitude a replay of `seq` feeds the tracker under `cfg`: its
    error model, gaps, and the local fit with its window widened against the
    recording's noise (sim_replay.attitude.attitude_for_replay)."""
    return attitude_for_replay(seq, attitude_error_model(cfg), cfg.replay.gt_max_gap_s,
                               cfg.ahrs.smoothing_s, cfg.ahrs.smoothing_max_s,
                               cfg.nislam.attitude_sd_deg)


def bench(
    seq_dir: Path | str, cfg: Config, max_frames: int | None = None, repeat: int = 1
) -> dict[str, Any]:
    """Per-frame `track()` times over the sequence, `repeat` passes with a
    fresh tracker each (so every pass includes the same key-frame work)."""
    pin_one_core()
    keep_freed_memory()  # as the service runs it
    cfg = with_tracker_resolved(cfg, service=False)
    seq = open_sequence(seq_dir, cfg.replay.assoc_max_dt_s, cfg.replay.undistort,
                        cfg.replay.stamp_window_s)
    attitude, _label = replay_attitude(seq, cfg)
    log.info("decoding %d frames into memory", len(seq) if max_frames is None else max_frames)
    frames, stages = read_timed(seq, max_frames)
    frame_ms: list[float] = []
    # The same by this thread's CPU time: what another process's load adds
    # to the wall time (waiting for a core) is left out, so figures taken on
    # a busy machine stay comparable.
    cpu_ms: list[float] = []
    backend_ms: list[float] = []  # FastORB's back-end slices, run after a frame and timed apart
    job_ms: list[float] = []  # ... summed per key frame (one local BA)
    loop_ms: list[float] = []  # loop closing: one key frame's query and check
    correct_ms: list[float] = []  # ... and each correction (pose graph, map moved)
    results: list[TrackResult] = []
    # by kind: a frame that starts a key or re-uses a kept one does more work
    kind_ms: dict[str, list[float]] = {"keyframe": [], "reused": [], "plain": []}
    kind_cpu_ms: dict[str, list[float]] = {k: [] for k in kind_ms}
    deferred_ms: list[float] = []  # finish_frame(): after the pose
    kind_deferred_ms: dict[str, list[float]] = {k: [] for k in kind_ms}
    parts_ms: dict[str, list[float]] = {}  # the fused tracker's parts (last_part_ms)
    for _ in range(repeat):
        tracker = make_tracker(cfg.tracker.name, seq.intrinsics, cfg)
        finish_frame = getattr(tracker, "finish_frame", None)
        for frame in frames:
            t0, c0 = time.perf_counter(), time.thread_time()
            result = tracker.track(frame, attitude)
            dt_ms = (time.perf_counter() - t0) * 1e3
            cpu_ms.append((time.thread_time() - c0) * 1e3)
            frame_ms.append(dt_ms)
            if len(results) < len(frames):
                results.append(result)
            # (a re-use decided after the last pose is a plain match here)
            kind = ("keyframe" if result.new_keyframe or result.keyframe_from_previous
                    else "reused" if result.keyframe_reused and not result.keyframe_withdrawn
                    else "plain")
            kind_ms[kind].append(dt_ms)
            kind_cpu_ms[kind].append(cpu_ms[-1])
            if finish_frame is not None:
                t0 = time.perf_counter()
                finish_frame()
                deferred_ms.append((time.perf_counter() - t0) * 1e3)
                kind_deferred_ms[kind].append(deferred_ms[-1])
            for part, ms in getattr(tracker, "last_part_ms", {}).items():
                parts_ms.setdefault(part, []).append(ms)
            step = getattr(tracker, "backend_step", None)
            if step is not None:
                t0 = time.perf_counter()
                if step():
                    backend_ms.append((time.perf_counter() - t0) * 1e3)
        for part in [tracker, *(link.tracker for link in getattr(tracker, "links", ()))]:
            mapping = getattr(part, "mapping", None)
            if mapping is not None:
                job_ms.extend(mapping.stats.job_ms)
            loops = getattr(part, "loops", None)
            if loops is not None:
                loop_ms.extend(loops.stats.query_ms)
                correct_ms.extend(loops.stats.correct_ms)
    by_kind: dict[str, Any] = {}
    for kind, ms in kind_ms.items():
        by_kind[f"{kind}_frames"] = len(ms) // repeat
        by_kind[f"{kind}_frames_ms_median"] = float(np.median(ms)) if ms else None
        c = kind_cpu_ms[kind]
        by_kind[f"{kind}_frames_cpu_ms_median"] = float(np.median(c)) if c else None
        d = kind_deferred_ms[kind]
        by_kind[f"{kind}_deferred_ms_median"] = float(np.median(d)) if d else None
    stages["tracker"] = frame_ms
    stages["tracker_deferred"] = deferred_ms
    stages.update(output_times(results, cfg))
    return {
        "sequence": str(Path(seq_dir).resolve()),
        "tracker": cfg.tracker.name,
        "frames": len(frames),
        "repeat": repeat,
        **frame_time_stats(frame_ms),
        "cpu_ms_median": float(np.median(cpu_ms)) if cpu_ms else None,
        "cpu_ms_p95": float(np.percentile(cpu_ms, 95)) if cpu_ms else None,
        **by_kind,
        "deferred_ms_median": float(np.median(deferred_ms)) if deferred_ms else None,
        "deferred_ms_p95": float(np.percentile(deferred_ms, 95)) if deferred_ms else None,
        **backend_stats(backend_ms, job_ms, loop_ms, correct_ms),
        "stages_ms": {k: stage_stats(v) for k, v in stages.items()},
        "parts_ms_median": {part: float(np.median(ms)) for part, ms in parts_ms.items()},
    }


def backend_stats(slice_ms: list[float], job_ms: list[float], loop_ms: list[float],
                  correct_ms: list[float]) -> dict[str, Any]:
    """The back end's time apart from tracking (FastORB's): per slice (one
    unit run after a frame), per key frame of local mapping (one local BA),
    per key frame of loop closing (place query and 3-D check) and per loop
    correction (pose graph and map moved)."""
    def q(a: list[float], p: float) -> float | None:
        return float(np.percentile(a, p)) if len(a) else None
    return {"backend_slices": len(slice_ms), "backend_slice_ms_median": q(slice_ms, 50),
            "backend_slice_ms_p95": q(slice_ms, 95), "backend_keyframes": len(job_ms),
            "backend_keyframe_ms_median": q(job_ms, 50), "backend_keyframe_ms_p95": q(job_ms, 95),
            "loop_queries": len(loop_ms), "loop_query_ms_median": q(loop_ms, 50),
            "loop_query_ms_p95": q(loop_ms, 95), "loop_corrections": len(correct_ms),
            "loop_correction_ms_median": q(correct_ms, 50)}


def stage_stats(ms: list[float]) -> dict[str, float | int | None]:
    return {**percentiles_ms(ms), "n": len(ms)}


def read_timed(seq: Any, max_frames: int | None) -> tuple[list[Any], dict[str, list[float]]]:
    """The frames decoded (and undistorted) into memory, each read timed
    ("source"), and the undistortion's two remaps timed again on their own."""
    maps = undistort_maps(seq.camera) if seq.camera.is_distorted else None
    frames: list[Any] = []
    read_ms: list[float] = []
    remap_ms: list[float] = []
    for i in range(len(seq)):
        if max_frames is not None and len(frames) >= max_frames:
            break
        t0 = time.perf_counter()
        frame = seq.read_frame(i)
        read_ms.append((time.perf_counter() - t0) * 1e3)
        if frame is None:
            continue
        frames.append(frame)
        if maps is not None:
            t0 = time.perf_counter()
            cv2.remap(frame.bgr, maps.color_map1, maps.color_map2, cv2.INTER_LINEAR)
            cv2.remap(frame.depth_m, maps.depth_map_x, maps.depth_map_y, cv2.INTER_NEAREST)
            remap_ms.append((time.perf_counter() - t0) * 1e3)
    return frames, {"source_read": read_ms, "undistortion": remap_ms}


def output_times(results: list[TrackResult], cfg: Config) -> dict[str, list[float]]:
    """The outputs' per-frame encoding on their own threads, without a link:
    the MAVLink sample and ODOMETRY packet, the zenoh pose's JSON, and each
    finished key frame's map message."""
    import json

    from onboard.outputs.mapcodec import MapKeyframe, encode_keyframe
    from onboard.outputs.mavlink import load_mavutil
    from onboard.outputs.mavlink_feed import VisionFeed, odometry_args
    from onboard.outputs.zenoh_out import pose_message

    mav = load_mavutil().mavlink.MAVLink(None, srcSystem=1, srcComponent=197)
    feed = VisionFeed.from_config(cfg.mavlink)
    out: dict[str, list[float]] = {"mavlink_encode": [], "zenoh_pose_encode": [],
                                   "zenoh_map_encode": []}
    for i, r in enumerate(results):
        t0 = time.perf_counter()
        sample = feed.update(r).sample
        if sample is not None:
            mav.odometry_encode(*odometry_args(sample)).pack(mav)
            out["mavlink_encode"].append((time.perf_counter() - t0) * 1e3)
        t0 = time.perf_counter()
        json.dumps(pose_message(r, i), allow_nan=False)
        out["zenoh_pose_encode"].append((time.perf_counter() - t0) * 1e3)
        for cloud in r.finished_keyframes:
            t0 = time.perf_counter()
            encode_keyframe(MapKeyframe.from_cloud(cloud))
            out["zenoh_map_encode"].append((time.perf_counter() - t0) * 1e3)
    return out
