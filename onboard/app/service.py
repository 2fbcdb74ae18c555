"""`nislam run`: the onboard service. One low-power loop on the calling thread:

    take the newest frame (stale ones are dropped by the camera's slot, never
    queued) -> the tracker, which looks the attitude up at the capture time
    -> the outputs (MAVLink, zenoh) -> the health state machine -> the
    tracker's work for the next frames (`finish_frame`: a new key, the key's
    refinement), once the pose is on its way -> the watchdog ping

Drivers (camera, AHRS, the autopilot link) run on their own threads, as do
the outputs' senders; nothing here blocks on a device or a socket for longer
than `[service] poll_s`, so a missing camera shows as lost and a hung loop
stops the watchdog pings (systemd then restarts us).

Sources: the hardware of the config (onboard.app.hardware), or a recorded or
synthetic sequence replayed at its own pace through the same interfaces
(sim_replay.sources). With ground truth (replays) the trusted poses are
scored at the end (ATE after SE(3) alignment) and written like `nislam
replay` writes them.

Stopping (SIGTERM/SIGINT set `stop`): the frame in hand is finished, the
last key frame goes to the map, the outputs flush, devices close.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from onboard.app.allocator import keep_freed_memory
from onboard.app.bench import pin_one_core
from onboard.app.config import Config, config_to_toml, with_tracker_resolved
from onboard.app.cpu_steal import CpuTicks, read_ticks, steal_share
from onboard.app.delivery import DeliveryWatch, delivery_lines
from onboard.app.health import HealthMonitor, HealthThresholds
from onboard.app.latency import LATENCY_FILE, LoopTiming, attach_timing
from onboard.app.loop_stats import (
    RUN_FILE,
    LoopStats,
    RunResult,
    jsonable,
    stats_line,
    write_run_json,
)
from onboard.app.priority import hand_gil_over_promptly, raise_to_realtime
from onboard.app.replay import (
    CONFIG_FILE,
    GT_AT_FRAMES_FILE,
    METRICS_FILE,
    TRAJECTORY_FILE,
    TrackLog,
    evaluate_track,
    write_text_atomic,
    write_trajectories,
)
from onboard.app.run_files import FileWrites, LiveTrajectory
from onboard.app.sdnotify import Notifier
from onboard.app.sources import Sources
from onboard.app.warm import warm_up
from onboard.core.camera import CameraIntrinsics
from onboard.core.messages import Health, HealthReport, Tracker, TrackResult
from onboard.core.pose_gate import PoseGate
from onboard.core.trajectory import write_tum
from onboard.fusion.registry import NEEDS_ATTITUDE, make_tracker
from onboard.fusion.switching import SwitchingTracker
from onboard.outputs.group import Output, make_outputs
from onboard.outputs.wake import Wake, defer_wakeups

log = logging.getLogger(__name__)

Emit = Callable[[str], None]
ATTITUDE_MARGIN_S = 0.005  # beyond the sample needed: interpolation brackets it
TrackerFactory = Callable[[str, CameraIntrinsics, Config], Tracker]


# --------------------------------------------------------------------------- statistics


# --------------------------------------------------------------------------- the loop


class Service:
    """The loop and what it owns; `run()` returns when stopped, when the
    replay ends or after `seconds`."""

    def __init__(
        self,
        cfg: Config,
        sources: Sources,
        stop: threading.Event,
        *,
        seconds: float | None = None,
        notifier: Notifier | None = None,
        emit: Emit | None = None,
        out_dir: Path | None = None,
        tracker_factory: TrackerFactory = make_tracker,
        realtime: bool = False,
    ) -> None:
        """`realtime`: raise the process to `[service] realtime_priority` once
        tracking (a process-wide setting: only the program's entry point asks)."""
        self.cfg = cfg = with_tracker_resolved(cfg, service=True)
        self.sc = cfg.service
        self.sources = sources
        self.stop = stop
        self.seconds = seconds
        self.notifier = notifier or Notifier(env={})
        self.emit = emit or (lambda line: log.info("%s", line))
        self.out_dir = out_dir
        self.tracker_factory = tracker_factory
        self.realtime = realtime
        self.stats = LoopStats()
        # Trusted poses are kept only to be scored or written: a service on
        # hardware without --out (or a looped soak) keeps nothing that grows.
        keep = sources.sequence is not None or (out_dir is not None and not sources.looped)
        self.track_log: TrackLog | None = TrackLog() if keep else None
        # ... and appended to trajectory.tum as the run goes (a full disk or a
        # kill then loses the last second, not the run: onboard.app.run_files)
        self.live = LiveTrajectory(out_dir / TRAJECTORY_FILE) if keep and out_dir else None
        self.writes = FileWrites()
        self.delivery = DeliveryWatch()  # "nobody may be receiving", told once
        self._outputs: Output | None = None
        self.tracker: SwitchingTracker | None = None
        self._backend_busy = False  # the tracker's back end had work on the last turn
        self.health = HealthMonitor(HealthThresholds(
            self.sc.frame_timeout_s, self.sc.degraded_gap_s, cfg.mavlink.degraded_quality,
            self.sc.start_grace_s, self.sc.recover_s), time.monotonic(), sources.devices)
        self.ready = False
        self.scheduling = "normal"  # what the process runs at (onboard.app.priority)
        self._ticks_at_start: CpuTicks | None = None
        self.gate = PoseGate()  # no pose the motion model cannot explain goes out trusted
        self._last_seq = 0
        self._offset_s = 0.0  # the tracker's attitude time offset, from its last result
        self._output_stats: dict[str, dict[str, Any]] = {}  # each output's counters at the end
        self._wakes: list[Wake] = []
        # Per-frame latency and stage times (onboard/app/latency.py); latency.csv with --out.
        self.timing = LoopTiming(sources.host_time_s,
                                 None if out_dir is None else out_dir / LATENCY_FILE)

    def run(self) -> RunResult:
        pin_one_core()
        keep_freed_memory()  # no page faults per frame (onboard/app/allocator.py)
        hand_gil_over_promptly()  # the loop waits < 1 ms for the GIL (onboard/app/priority.py)
        t_start = time.monotonic()
        outputs = make_outputs(self.cfg.mavlink, self.cfg.zenoh, mavlink_link=self.sources.link,
                               host_time_s=self.sources.host_time_s)
        attach_timing(outputs, self.timing, t_start)
        self._outputs = outputs
        drivers = self.sources.devices  # + the outputs' links (the zenoh router)
        self.health.devices = lambda: [*(drivers() if drivers else []), *outputs.device_states()]
        stop_times: dict[str, float] = {}
        # Announce "starting" before anything can block the loop.
        self._report(outputs, self.health.on_idle(time.monotonic()))
        # From here the outputs' threads are woken once a turn, when the loop
        # is done with its frame (onboard/outputs/wake.py: p95 12 ms saved).
        self._wakes = defer_wakeups(outputs)
        # Then compile the tracker's kernels (or load them from numba's cache).
        # Sources with devices to watch (hardware, the closed loop's link)
        # start first, so a missing device is told within a second or two
        # (frames of the warm-up only replace each other in the newest-frame
        # slot); a replay, whose clock is ours, starts after, so its first
        # frames meet a ready tracker (a cold cache takes ~9 s: 274 of
        # `make run`'s 600 frames were dropped on a fresh clone).
        devices_first = self.sources.devices is not None
        if devices_first:
            self.sources.start()
        warm_up()  # every tracker's kernels and the attitude buffer's fit: the fallback's too
        if not devices_first:
            self.sources.start()
        if self.live is not None:
            self.live.open()
        t_loop = time.monotonic()  # the run's length and rate count from here, not the warm-up
        self._ticks_at_start = read_ticks()  # the host's steal over the run (onboard/app/cpu_steal.py)
        # So does the wait for the first frame: a cold numba cache (~15 s on a
        # fresh clone) is not a camera that sends nothing (`make run` said
        # "lost: no frames from the camera for 14 s"). A missing device is
        # told by its driver's state, not by this wait.
        self.health.start_s = t_loop
        try:
            self.stats.period_start_s = t_loop
            self._loop(outputs, t_loop)
            self._finish(outputs)
        finally:
            self.notifier.stopping()
            try:
                outputs.close()
                self._output_stats = outputs.stats()
            finally:
                stop_times = self.sources.stop()
                self.notifier.close()
        return self._result(time.monotonic() - t_loop, stop_times)

    def _loop(self, outputs: Output, t_start: float) -> None:
        deadline = None if self.seconds is None else t_start + self.seconds
        poll = self.sc.poll_s
        camera = self.sources.camera
        while not self.stop.is_set():
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                break
            self.stats.loop_turns += 1
            for wake in self._wakes:  # what the last turn handed to the outputs
                wake.flush()
            self.timing.tick(now)
            self.notifier.watchdog()
            if self.tracker is None and not self._make_tracker(poll):
                self._idle(outputs, now)
                continue
            # Asked before waiting: a last frame put just before the source
            # closed is still taken on this turn or the next.
            exhausted = camera.exhausted
            got = camera.take(self._last_seq, 0.0 if self._backend_busy else poll)
            if got is None:
                if exhausted:
                    log.info("replay finished")
                    break
                # The idle time between frames runs the tracker's back end
                # (FastORB's local BA), one bounded slice per turn, so a new
                # frame waits at most one slice (docs/fastorb_backend.md).
                self._backend_busy = self.tracker.backend_step()
                if not self._backend_busy:
                    self._idle(outputs, time.monotonic())
                continue
            self._last_seq, frame = got
            self._frame(outputs, frame)
            self._backend_busy = True  # a new key frame may have queued work

    def _make_tracker(self, timeout_s: float) -> bool:
        """Build the tracker once the camera tells its intrinsics."""
        cam = self.sources.camera.wait_camera(timeout_s)
        if cam is None:
            return False
        intr = cam.intrinsics()
        primary = self.tracker_factory(self.cfg.tracker.name, intr, self.cfg)
        fb = self._fallback_name()
        make_fb = (lambda: self.tracker_factory(fb, intr, self.cfg)) if fb else None
        self.tracker = SwitchingTracker(primary, make_fb, self.sc.return_after_s)
        log.info("camera up: %dx%d, fx %.1f; tracker %s%s", intr.width, intr.height, intr.fx,
                 primary.name, f" (fallback {fb})" if fb else "")
        return True

    def _fallback_name(self) -> str:
        """`[service] fallback_tracker`, where the primary can use one: only a
        tracker that reports lost without the AHRS hands over to it (the fused
        tracker carries on through an attitude gap on FastORB by itself)."""
        return self.sc.fallback_tracker if self.cfg.tracker.name in NEEDS_ATTITUDE else ""

    def _frame(self, outputs: Output, frame: Any) -> None:
        tracker = self.tracker
        assert tracker is not None
        timing = self.timing
        timing.frame_start(frame.t_s)
        self._wait_for_attitude(frame.t_s)
        timing.lap()
        t0 = time.perf_counter()
        result = self.gate.check(tracker.track(frame, self.sources.attitude))
        timing.lap()
        withheld = self.gate.withheld  # a suspect step being checked: no pose, no "lost"
        if withheld:
            for kf in result.finished_keyframes:  # the map still gets its key frames
                outputs.publish_keyframe(kf)
        else:
            outputs.publish(result)
        timing.lap()
        ms = (time.perf_counter() - t0) * 1e3
        now = time.monotonic()
        report = self.health.on_idle(now) if withheld else self.health.on_frame(
            now, result, tracker.fallback.name if tracker.fallback is not None else None)
        self._report(outputs, report)
        self._log_result(result, ms)
        timing.lap()
        # The pose is handed over: wake the outputs' threads now (not at the
        # next turn), then the tracker's deferred work, which no pose waits for.
        for wake in self._wakes:
            wake.flush()
        tracker.finish_frame()
        timing.lap()
        timing.frame_end(result.trusted and result.p_W_m is not None and not withheld,
                         report.state is Health.TRACKING)
        if not self.ready:
            self.ready = True
            if self.realtime:
                self.scheduling = raise_to_realtime(self.sc.realtime_priority)
            self.notifier.ready(f"tracking with {tracker.name}: first frame in")
            log.info("ready: first frame tracked (%s)", report.state.value)
        self._maybe_stats(now)

    def _wait_for_attitude(self, t_s: float) -> None:
        """The tracker looks the attitude up at the capture time plus its
        offset estimate; a sample that late may still be on its way (a
        positive offset, an AHRS a little behind the camera, or its thread
        catching up after the machine stalled): wait for it, at most
        `attitude_wait_s`, when the AHRS is behind by no more than
        `[ahrs] max_age_s` (a silent AHRS costs no time: the tracker
        reports it)."""
        att = self.sources.attitude
        newest = att.newest()
        if newest is not None:  # how far the AHRS is ahead of the frame (negative: behind)
            self.stats.period_att_lead_ms = min(self.stats.period_att_lead_ms,
                                                (newest.t_s - t_s) * 1e3)
        need_s = t_s + max(0.0, self._offset_s) + ATTITUDE_MARGIN_S
        if newest is not None and 0.0 < need_s - newest.t_s <= self.cfg.ahrs.max_age_s:
            att.wait_covered(need_s, self.sc.attitude_wait_s)

    def _idle(self, outputs: Output, now: float) -> None:
        self.stats.idle_turns += 1
        self._report(outputs, self.health.on_idle(now))
        self._maybe_stats(now)

    def _report(self, outputs: Output, report: HealthReport) -> None:
        outputs.publish_health(report)
        if report.changed:
            self.stats.health_changes += 1
            level = logging.WARNING if report.state in (Health.LOST, Health.DEGRADED) else logging.INFO
            log.log(level, "health: %s (%s)", report.state.value, report.reason)

    def _log_result(self, result: TrackResult, ms: float) -> None:
        s = self.stats
        s.frames += 1
        s.period_frames += 1
        s.frame_ms.add(ms)
        s.period_ms.append(ms)
        s.keyframes += result.keyframes_added
        s.resets = result.reset_counter
        s.last_psr = result.psr
        self._offset_s = result.attitude_offset_s
        trusted = result.trusted and result.p_W_m is not None
        s.tracked += int(trusted)
        if not trusted:
            s.lost_reasons[result.lost_reason or "unknown"] += 1
        tl = self.track_log
        if tl is not None and trusted:
            q = result.q_W_C_xyzw
            tl.t_s.append(result.t_s)
            tl.p_W_m.append(result.p_W_m)
            tl.q_W_C_xyzw.append(q)
            tl.reference_keyframe_id.append(result.reference_keyframe_id)
            if self.live is not None:
                self.live.append(result.t_s, result.p_W_m, q)

    def _maybe_stats(self, now: float) -> None:
        s = self.stats
        span = now - s.period_start_s
        if span < self.sc.stats_period_s:
            return
        ms = np.asarray(s.period_ms) if s.period_ms else np.zeros(0)
        period = {
            "t_s": now,
            "health": self.health.report.state.value,
            "hz": s.period_frames / span,
            "ms_median": float(np.median(ms)) if len(ms) else None,
            "ms_p95": float(np.percentile(ms, 95)) if len(ms) else None,
            "ms_p99": float(np.percentile(ms, 99)) if len(ms) else None,
            "dropped": self._dropped(),
            "psr": s.last_psr,
            "keyframes": s.keyframes,
            "resets": s.resets,
            "attitude_offset_ms": self._offset_s * 1e3,
            "attitude_lead_ms_min": s.period_att_lead_ms,
        }
        s.periods.append(period)
        if self._outputs is not None:
            self.delivery.check(self._outputs, now)
        line = stats_line(period, self.tracker)
        if self.health.report.devices:  # each driver's state (drivers/device_state.py)
            line += "  " + ", ".join(self.health.report.devices)
        self.emit(line)
        self.notifier.status(line)
        s.period_ms = []
        s.period_att_lead_ms = float("inf")
        s.period_frames = 0
        s.period_start_s = now

    def _frames_offered(self) -> int:
        """Frames the source had for us: into the camera's slot, or skipped
        by a replay that could not decode them in time."""
        slot = getattr(self.sources.camera, "slot", None)
        put = self.stats.frames if slot is None else int(slot.stats.put)
        return put + int(getattr(self.sources.camera, "late", 0))

    def _dropped(self) -> int:
        slot = getattr(self.sources.camera, "slot", None)
        return 0 if slot is None else int(slot.stats.dropped)

    def _finish(self, outputs: Output) -> None:
        if self.tracker is None:
            return
        last = self.tracker.finish()
        if last is not None:
            outputs.publish_keyframe(last)

    # ------------------------------------------------------------ the result
    def _result(self, seconds: float, stop_times: dict[str, float]) -> RunResult:
        s, tr = self.stats, self.tracker
        metrics: dict[str, Any] = {
            "source": self.sources.label,
            "attitude_source": self.sources.attitude_label,
            "tracker": self.cfg.tracker.name,
            "fallback_tracker": self._fallback_name(),
            "seconds": seconds,
            "frames": s.frames,
            "frames_tracked": s.tracked,
            "frames_dropped": self._dropped(),
            # A replay that could not decode in time skips frames before the
            # slot sees them (sim_replay.sources.ReplayCamera): not "dropped".
            "frames_late_at_source": int(getattr(self.sources.camera, "late", 0)),
            "frame_hz": s.frames / seconds if seconds > 0 else 0.0,
            "keyframes": s.keyframes,
            "reset_counter": s.resets,
            "tracker_switches": 0 if tr is None else tr.switches,
            "pose_gate": self.gate.stats.as_dict(),
            "lost_reasons": dict(s.lost_reasons),
            "health": self.health.report.state.value,
            "health_changes": s.health_changes,
            "loop_turns": s.loop_turns,
            "stop_times_s": stop_times,
            "periods": list(s.periods),
            **s.frame_ms.stats(),
        }
        if tr is not None and hasattr(tr.primary, "stats"):  # the fused tracker
            metrics["fusion"] = tr.primary.stats()
        if self.sources.source_stats is not None:
            metrics["source_stats"] = self.sources.source_stats()
        self.timing.finish()
        steal = steal_share(self._ticks_at_start, read_ticks())
        host = "" if steal is None else f"; the host stole {100 * steal:.1f} % of the CPUs' time"
        metrics["latency_lines"] = [*self.timing.summary_lines(self._output_stats),
                                    f"scheduling  {self.scheduling}{host} (onboard/app/priority.py, cpu_steal.py)"]
        if self.sources.host_mapping is not None:
            # The MAVLink feed's time_usec is on the host's monotonic clock; the
            # trajectories keep the recording's stamps: how one maps onto the other.
            metrics["host_clock"] = self.sources.host_mapping()
        seq = self.sources.sequence
        if seq is not None:
            metrics["skipped"] = seq.skipped.as_dict()  # what the reader left out, by kind
        if self.live is not None:
            self.live.close()
        out, attempt = self.out_dir, self.writes.attempt
        if seq is not None and self.track_log is not None and s.frames:
            ev = evaluate_track(self.track_log, seq, self.cfg.replay.gt_max_gap_s)
            metrics["evaluation_note"] = ev.note
            if ev.metrics is not None:
                metrics.update(ev.metrics.as_dict())
            if out is not None:
                with attempt(out / TRAJECTORY_FILE, out / GT_AT_FRAMES_FILE):
                    out.mkdir(parents=True, exist_ok=True)
                    write_trajectories(ev, out)
        elif out is not None and self.track_log is not None:
            with attempt(out / TRAJECTORY_FILE):
                out.mkdir(parents=True, exist_ok=True)
                est = self.track_log.trajectory()
                write_tum(out / TRAJECTORY_FILE, est.t_s, est.p_xyz_m, est.q_xyzw)
        metrics["output_notes"] = delivery_lines(self._output_stats)
        if out is not None:
            with attempt(out / CONFIG_FILE, out / METRICS_FILE):
                out.mkdir(parents=True, exist_ok=True)
                write_text_atomic(out / CONFIG_FILE, config_to_toml(self.cfg))
                kept = {k: v for k, v in metrics.items() if k != "latency_lines"}
                write_text_atomic(out / METRICS_FILE,
                                  json.dumps(jsonable(kept), indent=2, allow_nan=False) + "\n")
            zs = self._output_stats.get("zenoh")
            with attempt(out / RUN_FILE):
                write_run_json(out, {
                    "keyframes_published": None if zs is None else zs["keyframes_published"],
                    "keyframe_crc32": None if zs is None else zs["keyframe_crc32"],
                    **self.timing.run_fields(self._frames_offered(), s.resets, self._output_stats),
                    "scheduling": self.scheduling,
                    "host_steal_share": steal,
                    "outputs": self._output_stats,
                })
        notes = metrics["output_notes"]
        live_failed = self.live is not None and self.live.failed
        if live_failed:
            notes.append(f"recording stopped: {self.live.failed}")
        if out is not None:  # trajectory.tum's failure was told when it happened
            line = self.writes.report(out, skip=(TRAJECTORY_FILE,) if live_failed else ())
            if line:
                notes.append(f"recording: {line}")
        return RunResult(metrics, self.out_dir)


