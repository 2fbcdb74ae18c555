"""`nislam replay` as a function: track a recorded sequence end to end, score
it against ground truth and write the results into one folder.

Only our own result files in the output folder are (over)written; anything
else there is left alone.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import os
import sys
import time
from dataclasses import dataclass, field
from itertools import islice
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from onboard import NislamError
from onboard.app.allocator import keep_freed_memory
from onboard.app.bench import frame_time_stats, pin_one_core, replay_attitude
from onboard.app.config import Config, config_to_toml, with_tracker_resolved
from onboard.app.keyframe_anchors import KeyframeAnchors
from onboard.core.evaluation import (
    RPE_LAGS_FRAMES,
    TrajectoryMetrics,
    evaluate,
    ground_truth_at,
)
from onboard.core.messages import AttitudeSource, KeyframeCloud, Tracker, TrackResult
from onboard.core.trajectory import Trajectory, write_tum
from onboard.fusion.coverage import sigma1_coverage
from onboard.fusion.registry import make_tracker
from onboard.outputs.plot import plot_trajectory
from onboard.outputs.ply import write_ply
from sim_replay.attitude import stated_noise_deg
from sim_replay.tum import Sequence, open_sequence

log = logging.getLogger(__name__)

TRAJECTORY_FILE = "trajectory.tum"
# Ground truth at exactly the stamps of trajectory.tum: evo_ape pairs rows by stamp.
GT_AT_FRAMES_FILE = "groundtruth_at_frames.tum"
METRICS_FILE = "metrics.json"
CONFIG_FILE = "config.toml"
PLOT_FILE = "trajectory.png"
MAP_FILE = "map.ply"
RESULT_FILES = (TRAJECTORY_FILE, GT_AT_FRAMES_FILE, METRICS_FILE, CONFIG_FILE, PLOT_FILE, MAP_FILE)

RPE_DELTA_S = 1.0


@dataclass
class TrackLog:
    """What the tracking loop collected; poses only for trusted frames."""

    t_s: list[float] = field(default_factory=list)
    p_W_m: list[np.ndarray] = field(default_factory=list)
    q_W_C_xyzw: list[np.ndarray] = field(default_factory=list)
    reference_keyframe_id: list[int] = field(default_factory=list)  # per pose, -1 = unknown
    var_p_m2: list[np.ndarray] = field(default_factory=list)  # reported position variances
    frame_ms: list[float] = field(default_factory=list)
    lost_reasons: collections.Counter = field(default_factory=collections.Counter)
    keyframes: int = 0
    resets: int = 0
    attitude_offset_s: float | None = None
    keyframes_reused: int = 0
    clouds: dict[int, KeyframeCloud] = field(default_factory=dict)  # by id: a kept key's newest
    backend_ms: list[float] = field(default_factory=list)  # FastORB's back-end slices, timed apart
    anchors: KeyframeAnchors | None = None  # for the final trajectory (trackers with a back end)

    @property
    def frames(self) -> int:
        return len(self.frame_ms)

    def add_pose(self, result: TrackResult) -> None:
        """Keep a trusted result's pose, key and reported variances."""
        self.t_s.append(result.t_s)
        self.p_W_m.append(result.p_W_m)
        self.q_W_C_xyzw.append(result.q_W_C_xyzw)
        self.reference_keyframe_id.append(result.reference_keyframe_id)
        self.var_p_m2.append(np.asarray(result.pose_var[:3], dtype=np.float64))

    def trajectory(self) -> Trajectory:
        n = len(self.t_s)
        return Trajectory(
            np.asarray(self.t_s, dtype=np.float64),
            np.asarray(self.p_W_m, dtype=np.float64).reshape(n, 3),
            np.asarray(self.q_W_C_xyzw, dtype=np.float64).reshape(n, 4),
        )


@dataclass
class Evaluation:
    """The estimate as written, its ground truth at the same stamps (None when
    there is none) and the metrics; `note` says why metrics are missing."""

    estimate: Trajectory
    groundtruth: Trajectory | None
    metrics: TrajectoryMetrics | None
    frames_without_groundtruth: int
    note: str | None


@dataclass
class ReplayResult:
    metrics: dict[str, Any]
    out_dir: Path
    paths: dict[str, Path]
    plot_note: str | None = None  # why trajectory.png was not written

    def summary_lines(self) -> list[str]:
        """A one-screen summary of the run."""
        m = self.metrics
        lines = [
            f"sequence    {m['sequence']}  (tracker {m['tracker']})",
            f"frames      {m['frames']}  (skipped inputs: {_skipped_text(m['skipped'])})",
            f"tracked     {m['frames_tracked']} ({100.0 * m['tracked_share']:.1f} %), "
            f"lost {m['frames_lost']}{_reasons_text(m['lost_reasons'])}",
            f"key frames  {m['keyframes']} new, {m['keyframes_reused']} re-used; "
            f"resets {m['resets']}",
        ]
        if m["ate_rmse_m"] is None:
            lines.append(f"ATE / RPE   not computed: {m['evaluation_note']}")
        else:
            lines.append(
                f"ATE RMSE    {m['ate_rmse_m']:.4f} m over {m['frames_evaluated']} frames "
                f"(SE(3)-aligned)"
            )
            lines.append(f"RPE ({m['rpe_delta_s']:g} s)   {_rpe_text(m)}")
            lines += lag_lines(m)
        if m.get("loops_detected") is not None:
            final = m.get("ate_final_rmse_m")
            lines.append(f"loops       {m['loops_detected']} detected, {m['loops_accepted']} "
                         f"accepted, {m['loop_corrections']} corrections; final ATE "
                         + ("n/a" if final is None else f"{final:.4f} m (key frames' final poses)"))
        lines.append(
            f"time        median {_ms(m['frame_ms_median'])}, p95 {_ms(m['frame_ms_p95'])}, "
            f"max {_ms(m['frame_ms_max'])} per frame ({_hz(m['hz'])})"
        )
        offset = m["attitude_offset_s"]
        offset_text = "n/a" if offset is None else f"{offset * 1e3:+.1f} ms"
        lines.append(f"attitude    {m['attitude_source']}")
        lines.append(f"            time offset estimate {offset_text}")
        lines.append(f"frame times {m['frame_stamps']}")
        lines.append(f"output      {self.out_dir}")
        if self.plot_note is not None:
            lines.append(f"plot        skipped: {self.plot_note}")
        return lines


# --------------------------------------------------------------------------- run


def replay(
    seq_dir: Path | str,
    cfg: Config,
    out_dir: Path | str,
    max_frames: int | None = None,
    progress: bool = True,
) -> ReplayResult:
    """Track `seq_dir` with `cfg`, write the results into `out_dir`."""
    if max_frames is not None and max_frames < 1:
        raise NislamError(f"max_frames must be >= 1, got {max_frames}")
    pin_one_core()
    keep_freed_memory()
    out_dir = Path(out_dir)
    seq = open_sequence(seq_dir, cfg.replay.assoc_max_dt_s, cfg.replay.undistort,
                        cfg.replay.stamp_window_s)
    attitude, attitude_label = replay_attitude(seq, cfg)
    cfg = with_stated_ahrs(with_tracker_resolved(cfg, service=False), seq.path)
    tracker = make_tracker(cfg.tracker.name, seq.intrinsics, cfg)
    _make_out_dir(out_dir)  # before tracking: a bad --out should not cost a whole run

    track_log = track_sequence(tracker, seq, attitude, max_frames, progress)
    if track_log.frames == 0:
        raise NislamError(f"{seq_dir}: no frame could be decoded")
    ev = evaluate_track(track_log, seq, cfg.replay.gt_max_gap_s)

    paths = {name: out_dir / name for name in RESULT_FILES}
    write_trajectories(ev, out_dir)
    plot_note = _write_plot(ev, paths[PLOT_FILE], f"{seq.path.name}, {tracker.name}")
    map_points = _write_map(list(track_log.clouds.values()), paths[MAP_FILE])
    write_text_atomic(paths[CONFIG_FILE], config_to_toml(cfg))
    metrics = build_metrics(
        seq, cfg, track_log, ev, attitude_label, map_points, plot_written=plot_note is None
    )
    metrics["sigma1_coverage"] = _coverage(track_log, seq, cfg.replay.gt_max_gap_s)
    metrics.update(_backend_metrics(tracker, track_log, seq, cfg.replay.gt_max_gap_s))
    if hasattr(tracker, "stats"):  # the fused tracker: who contributed, who was left out
        metrics["fusion"] = tracker.stats()
    mapping = getattr(tracker, "mapping", None)
    if mapping is not None:  # FastORB's local mapping (docs/fastorb_backend.md)
        st = mapping.stats
        metrics["local_mapping"] = {"bundle_adjustments": st.jobs,
                                    "culled_keyframes": st.culled_keyframes,
                                    "erased_observations": st.erased_observations}
    write_text_atomic(paths[METRICS_FILE], json.dumps(metrics, indent=2, allow_nan=False) + "\n")
    written = {name: p for name, p in paths.items() if p.exists()}
    return ReplayResult(metrics, out_dir, written, plot_note)


def with_stated_ahrs(cfg: Config, seq_dir: Path | str) -> Config:
    """`cfg` with NI-SLAM told the attitude noise a simulated flight states
    (sim_replay.attitude.stated_noise_deg); unchanged for a real recording."""
    stated = stated_noise_deg(seq_dir)
    if stated is None or stated == cfg.nislam.attitude_sd_deg:
        return cfg
    log.info("%s: the AHRS's noise as simulated, %g deg (not %g)", seq_dir, stated,
             cfg.nislam.attitude_sd_deg)
    return dataclasses.replace(cfg, nislam=dataclasses.replace(cfg.nislam, attitude_sd_deg=stated))


def track_sequence(
    tracker: Tracker,
    seq: Sequence,
    attitude: AttitudeSource,
    max_frames: int | None,
    progress: bool,
) -> TrackLog:
    """Feed every frame to the tracker, timing `track()` alone."""
    out = TrackLog()
    total = len(seq) if max_frames is None else min(len(seq), max_frames)
    frames = islice(seq.frames(), max_frames)
    backend_step = getattr(tracker, "backend_step", None)
    finish_frame = getattr(tracker, "finish_frame", None)  # its work for the next frames
    pose_of = getattr(tracker, "keyframe_pose", None)
    out.anchors = None if pose_of is None else KeyframeAnchors(pose_of)
    # disable=None lets tqdm switch itself off when stderr is not a terminal.
    with tqdm(frames, total=total, unit="frame", desc=seq.path.name, file=sys.stderr,
              disable=None if progress else True) as bar:
        for frame in bar:
            t0 = time.perf_counter()
            result = tracker.track(frame, attitude)
            if finish_frame is not None:  # timed with track(): the frame's whole cost
                finish_frame()
            out.frame_ms.append((time.perf_counter() - t0) * 1e3)
            if backend_step is not None:  # one unit of back-end work in the frame's idle time
                t0 = time.perf_counter()
                if backend_step():
                    out.backend_ms.append((time.perf_counter() - t0) * 1e3)
            if result.trusted:
                out.add_pose(result)
                if out.anchors is not None:
                    out.anchors.add(result)
            else:
                out.lost_reasons[result.lost_reason or "unknown"] += 1
            out.keyframes += result.keyframes_added
            out.keyframes_reused += int(result.keyframe_reused)
            out.resets = result.reset_counter
            out.attitude_offset_s = result.attitude_offset_s
            for cloud in result.finished_keyframes:
                out.clouds[cloud.keyframe_id] = cloud
    last = tracker.finish()
    if last is not None:
        out.clouds[last.keyframe_id] = last
    return out


def evaluate_track(track_log: TrackLog, seq: Sequence, gt_max_gap_s: float) -> Evaluation:
    """Ground truth at the tracked frames' stamps, ATE and RPE.

    Tracked frames without ground truth (outside it or in a gap longer than
    `gt_max_gap_s`) are dropped from the estimate too, so the two trajectories
    written share every stamp, as evo_ape expects.
    """
    est = track_log.trajectory()
    if seq.groundtruth is None:
        return Evaluation(est, None, None, 0, "the sequence has no ground truth")
    if len(est) == 0:
        return Evaluation(est, None, None, 0, "no frame was tracked")
    gt, valid = ground_truth_at(est.t_s, seq.groundtruth, gt_max_gap_s)
    missing = int((~valid).sum())
    if len(gt) < 2:
        return Evaluation(est, None, None, missing, "fewer than 2 tracked frames have ground truth")
    if missing:
        log.info("%d tracked frames have no ground truth; left out of the evaluation", missing)
    est = est.slice_valid(valid)
    ref_ids = np.asarray(track_log.reference_keyframe_id, dtype=np.int64)
    # A log filled without key ids (another loop) leaves the key metrics out.
    ref_ids = ref_ids[valid] if len(ref_ids) == len(valid) else None
    metrics = evaluate(est, gt, rpe_delta_s=RPE_DELTA_S, reference_keyframe_id=ref_ids)
    return Evaluation(est, gt, metrics, missing, None)


def _backend_metrics(tracker: Tracker, track_log: TrackLog, seq: Sequence,
                     gt_max_gap_s: float) -> dict[str, Any]:
    """Loop closing's counts, and the ATE of the final trajectory (frames on
    their key frames' final poses, keyframe_anchors.py); None without them."""
    stats = getattr(getattr(tracker, "loops", None), "stats", None)
    out: dict[str, Any] = {
        "loops_detected": None if stats is None else stats.detected,
        "loops_accepted": None if stats is None else stats.accepted,
        "loop_corrections": None if stats is None else stats.corrections,
        "loop_query_ms_median": _median(None if stats is None else stats.query_ms),
        "loop_query_ms_max": None if stats is None or not stats.query_ms else max(stats.query_ms),
        "loop_correct_ms_median": _median(None if stats is None else stats.correct_ms),
        "ate_final_rmse_m": None,
    }
    if track_log.anchors is None or seq.groundtruth is None or not track_log.t_s:
        return out
    est = track_log.anchors.final(track_log.trajectory())
    gt, valid = ground_truth_at(est.t_s, seq.groundtruth, gt_max_gap_s)
    if valid.sum() >= 2:
        m = evaluate(est.slice_valid(valid), gt, rpe_delta_s=RPE_DELTA_S)
        out["ate_final_rmse_m"] = m.ate_rmse_m
    return out


def _median(values: list[float] | None) -> float | None:
    return None if not values else float(np.median(values))


def _coverage(track_log: TrackLog, seq: Sequence, gt_max_gap_s: float) -> float | None:
    """Share of the position error the reported 1-sigma covers (onboard.fusion.coverage)."""
    if seq.groundtruth is None or not track_log.t_s:
        return None
    est = track_log.trajectory()
    gt, valid = ground_truth_at(est.t_s, seq.groundtruth, gt_max_gap_s)
    var = np.asarray(track_log.var_p_m2, dtype=np.float64).reshape(-1, 3)[valid]
    return sigma1_coverage(est.p_xyz_m[valid], var, gt.p_xyz_m)


def build_metrics(
    seq: Sequence,
    cfg: Config,
    track_log: TrackLog,
    ev: Evaluation,
    attitude_label: str,
    map_points: int,
    plot_written: bool,
) -> dict[str, Any]:
    """Everything metrics.json holds; JSON-able, missing values as None."""
    frames = track_log.frames
    tracked = len(track_log.t_s)
    accuracy: dict[str, Any] = {
        "ate_rmse_m": None, "ate_mean_m": None, "ate_median_m": None, "ate_max_m": None,
        "rpe_trans_rmse_m": None, "rpe_rot_rmse_deg": None, "rpe_delta_s": RPE_DELTA_S,
        "rpe_pairs": 0, "frames_evaluated": 0,
        **{f"rpe_lag{k}_m": None for k in RPE_LAGS_FRAMES}, "rpe_rot_lag1_deg": None,
        "path_length_ratio": None, "keyframe_changes": 0,
        "keyframe_jump_median_m": None, "keyframe_jump_max_m": None,
    }
    if ev.metrics is not None:
        accuracy.update(ev.metrics.as_dict())
    timing = frame_time_stats(track_log.frame_ms)
    return {
        "sequence": str(seq.path.resolve()),
        "tracker": cfg.tracker.name,
        "frames": frames,
        "frames_tracked": tracked,
        "frames_lost": frames - tracked,
        "tracked_share": tracked / frames if frames else 0.0,
        "lost_reasons": dict(track_log.lost_reasons),
        "keyframes": track_log.keyframes,
        "keyframes_reused": track_log.keyframes_reused,
        "resets": track_log.resets,
        **accuracy,
        "frames_without_groundtruth": ev.frames_without_groundtruth,
        "evaluation_note": ev.note,
        **timing,
        "attitude_source": attitude_label,
        "attitude_offset_s": track_log.attitude_offset_s,
        "skipped": seq.skipped.as_dict(),  # every reader count (sim_replay.tum.SkipCounts)
        "frame_stamps": seq.stamps.describe() if seq.stamps is not None else "stamps as recorded",
        "map_points": map_points,
        "keyframe_clouds": len(track_log.clouds),
        "plot_written": plot_written,
    }


# --------------------------------------------------------------------------- outputs


def _make_out_dir(out_dir: Path) -> None:
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise NislamError(f"cannot create output folder {out_dir}: {e.strerror}") from None


def write_trajectories(ev: Evaluation, out_dir: Path) -> None:
    """trajectory.tum, and groundtruth_at_frames.tum when there is ground truth."""
    est = ev.estimate
    write_tum(out_dir / TRAJECTORY_FILE, est.t_s, est.p_xyz_m, est.q_xyzw)
    gt_path = out_dir / GT_AT_FRAMES_FILE
    if ev.groundtruth is None:
        # A file from an earlier run would pair with this run's trajectory.
        gt_path.unlink(missing_ok=True)
        return
    gt = ev.groundtruth
    write_tum(gt_path, gt.t_s, gt.p_xyz_m, gt.q_xyzw)


def _write_plot(ev: Evaluation, path: Path, title: str) -> str | None:
    """Write trajectory.png; returns why it was skipped, or None."""
    m = ev.metrics
    if m is None or ev.groundtruth is None:
        path.unlink(missing_ok=True)
        return "no ground truth to plot against"
    if not plot_trajectory(
        path, m.estimate_aligned_xyz_m, ev.groundtruth.p_xyz_m, m.t_s, m.ate_errors_m,
        f"{title}: ATE RMSE {m.ate_rmse_m:.3f} m, per-frame RPE {m.rpe_lag1_m * 1e3:.1f} mm",
        step_errors_m=m.step_errors_m, key_change=m.key_change,
    ):
        path.unlink(missing_ok=True)
        return "matplotlib is not installed (pip install 'nislam-onboard[plot]')"
    return None


def _write_map(clouds: list[KeyframeCloud], path: Path) -> int:
    """All key-frame clouds in one PLY; returns the number of points. Runs
    after the loop so the conversion never counts as tracking time."""
    parts = [c.points() for c in clouds]
    xyz = np.concatenate([p[0] for p in parts]) if parts else np.zeros((0, 3), np.float32)
    rgb = np.concatenate([p[1] for p in parts]) if parts else np.zeros((0, 3), np.uint8)
    write_ply(path, xyz, rgb)
    return len(xyz)


def write_text_atomic(path: Path, text: str) -> None:
    """Temp file then rename: a reader never sees half a file. Plain open()
    rather than mkstemp so the file gets the user's umask, not mode 0600."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


# --------------------------------------------------------------------------- summary text


def _ms(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.1f} ms"


def _hz(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.0f} Hz"


def _rpe_text(m: dict[str, Any]) -> str:
    if m["rpe_trans_rmse_m"] is None:
        return "n/a (no frame pair spans the delta)"
    return (f"{m['rpe_trans_rmse_m']:.4f} m, {m['rpe_rot_rmse_deg']:.2f} deg "
            f"({m['rpe_pairs']} pairs)")


def lag_lines(m: dict[str, Any]) -> list[str]:
    """The frame-lag RPE, path length ratio and key-change jumps of a metrics dict."""
    def mm(v: float | None) -> str:
        return "n/a" if v is None else f"{v * 1e3:.1f}"

    lags = ", ".join(f"{k} {mm(m.get(f'rpe_lag{k}_m'))}" for k in RPE_LAGS_FRAMES)
    rot = m.get("rpe_rot_lag1_deg")
    ratio = m.get("path_length_ratio")
    return [
        f"RPE frames  {lags} mm (lag 1, 3, 10, 30 frames); "
        f"rotation lag 1 {'n/a' if rot is None else f'{rot:.3f}'} deg",
        f"path ratio  {'n/a' if ratio is None else f'{ratio:.2f}'} (estimated / true length)",
        f"key changes {m.get('keyframe_changes', 0)}, error jump median "
        f"{mm(m.get('keyframe_jump_median_m'))} mm, max {mm(m.get('keyframe_jump_max_m'))} mm",
    ]


def _skipped_text(skipped: dict[str, int]) -> str:
    parts = [f"{k.replace('_', ' ')} {v}" for k, v in skipped.items() if v]
    return ", ".join(parts) if parts else "none"


def _reasons_text(reasons: dict[str, int]) -> str:
    if not reasons:
        return ""
    return " (" + ", ".join(f"{r}: {n}" for r, n in sorted(reasons.items())) + ")"
