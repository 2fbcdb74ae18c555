"""When each pose is true and when it arrives: per-frame latency and where the
loop's time goes, for `nislam run` (run.json, the zenoh status, the summary).

Every time here is on the host's monotonic clock, the clock of the capture
stamps (depthai stamps with it; a replay's stamps are mapped onto it by
`host_time_s`) and of the MAVLink feed's `time_usec`. Per frame:

    capture -> taken        the camera's delivery and the newest-frame slot ("source")
            -> attitude     waiting for the AHRS sample that covers the capture
            -> tracker      `track()`; its end is "done" (capture -> done)
            -> publish      handing the result to the outputs (queues)
            -> health       the health state machine and its report
            -> deferred     the tracker's work for the next frames (its key's
                            refinement, a new key), after the pose went out
    (sender thread)  -> written   the MAVLink pose written to the link (capture -> written)
    (the link)       -> arrival   written + the link's one-way time, from our own
                                  TIMESYNC round trips (onboard/outputs/mavlink_timesync.py)

Percentiles come from fixed-bin histograms (loop_stats.MsHistogram): constant
memory however long the service runs. The MAVLink sender reports each pose it
wrote through `on_written` (its own thread: one histogram add), the zenoh
publisher its encode-and-put times through `on_stage`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from onboard.app.loop_stats import MsHistogram, percentiles_ms

log = logging.getLogger(__name__)

LOOP_STAGES = ("source", "attitude_wait", "tracker", "publish", "health", "deferred")
LATENCY_FILE = "latency.csv"
CSV_HEADER = ("capture_s,source_ms,attitude_wait_ms,tracker_ms,publish_ms,health_ms,"
              "deferred_ms,done_ms,written_ms,trusted\n")
WINDOW = 300  # frames in the status's recent percentiles (10 s at 30 Hz)


def percentiles(h: MsHistogram) -> dict[str, float | None]:
    return {"p50": h.percentile(50), "p95": h.percentile(95), "p99": h.percentile(99),
            "max": h.max_ms if h.n else None, "n": h.n}


def process_start_monotonic() -> float | None:
    """This process's start on time.monotonic()'s clock (Linux /proc), or None."""
    try:
        import os

        fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        start_ticks = int(fields[19])  # field 22, starttime, in clock ticks since boot
        boot_now = time.clock_gettime(time.CLOCK_BOOTTIME)
        age_s = boot_now - start_ticks / os.sysconf("SC_CLK_TCK")
        return time.monotonic() - age_s
    except (OSError, ValueError, IndexError, AttributeError):
        return None


class LoopTiming:
    """Per-frame marks of the loop thread, latencies from the output threads,
    and what run.json, the status and the summary say about them."""

    def __init__(self, host_time_s: Callable[[float], float] | None = None,
                 csv_path: Path | None = None, minute_s: float = 60.0) -> None:
        self.host_time_s = host_time_s
        self.stages = {s: MsHistogram() for s in LOOP_STAGES}
        self.done = MsHistogram()  # capture -> tracker done
        self.written = MsHistogram()  # capture -> MAVLink written (sender thread)
        self.arrival = MsHistogram()  # written + one-way link time (TIMESYNC)
        self.frame_loop = MsHistogram()  # taken -> health reported (the loop's own time)
        # The loop thread's CPU time in track() and in the whole frame: on a
        # busy machine wall time also counts the time other jobs had the
        # core; CPU time is what the frame itself cost.
        self.tracker_cpu = MsHistogram()
        self.frame_cpu = MsHistogram()
        self._cpu: list[float] = []
        self.other: dict[str, MsHistogram] = {}  # output threads' stages (encode, send)
        self._other_lock = threading.Lock()
        self._recent = np.zeros(WINDOW)  # capture -> written (or done) of the last frames
        self._recent_n = 0
        self._minute = {"done": MsHistogram(), "written": MsHistogram()}
        self._minute_s = minute_s
        self._minute_start: float | None = None
        self.minutes: list[dict[str, Any]] = []
        self.one_way_s: Callable[[], float | None] = lambda: None  # set by attach_timing()
        self.timesync: Callable[[], dict[str, Any] | None] = lambda: None
        self.autopilot_timesyncs: Callable[[], bool] = lambda: False  # we answered its requests
        self.process_start_s = process_start_monotonic()
        self.service_start_s = time.monotonic()
        self.first_pose_at: float | None = None
        self.frames = 0
        self.good_frames = 0  # frames after which the health was "tracking"
        self.first_frame_at: float | None = None
        self.last_frame_at: float | None = None
        self._marks: list[float] = []
        self._capture = 0.0
        self._row: list[float] = []
        self._csv_path = csv_path
        self._csv_rows: list[list[float]] = []
        self._csv_written: dict[int, float] = {}  # capture µs -> written ms (sender thread)
        self._csv_file: Any = None
        if csv_path is not None:
            csv_path.parent.mkdir(parents=True, exist_ok=True)
            self._csv_file = csv_path.open("w")
            self._csv_file.write(CSV_HEADER)

    # ------------------------------------------------------------ the loop thread
    def capture_host_s(self, t_s: float) -> float:
        return t_s if self.host_time_s is None else self.host_time_s(t_s)

    def frame_start(self, t_s: float) -> None:
        """The loop took a frame captured at `t_s` (source clock)."""
        now = time.monotonic()
        self._capture = self.capture_host_s(t_s)
        self._marks = [self._capture, now]
        self._cpu = [time.thread_time()]

    def lap(self) -> None:
        """The end of the next stage of LOOP_STAGES (after "source")."""
        self._marks.append(time.monotonic())
        self._cpu.append(time.thread_time())

    def frame_end(self, trusted: bool, good: bool) -> None:
        m = self._marks
        now = m[-1]
        ms = [(b - a) * 1e3 for a, b in zip(m[:-1], m[1:], strict=False)]
        for name, v in zip(LOOP_STAGES, ms, strict=False):
            self.stages[name].add(max(v, 0.0))
        done_ms = (m[3] - m[0]) * 1e3 if len(m) > 3 else (now - m[0]) * 1e3
        done_ms = max(done_ms, 0.0)
        self.done.add(done_ms)
        self._minute["done"].add(done_ms)
        self.frame_loop.add((now - m[1]) * 1e3)
        c = self._cpu
        if len(c) > 2:  # taken, attitude, tracker, ...
            self.tracker_cpu.add(max(c[2] - c[1], 0.0) * 1e3)
            self.frame_cpu.add(max(c[-1] - c[0], 0.0) * 1e3)
        if not self.written.n:  # no link: the status's recent figures are capture -> done
            self._push_recent(done_ms)
        self.frames += 1
        self.good_frames += int(good)
        if self.first_frame_at is None:
            self.first_frame_at = m[1]
        self.last_frame_at = m[1]
        if trusted and self.first_pose_at is None:
            self.first_pose_at = m[3] if len(m) > 3 else now
        if self._csv_file is not None:
            self._csv_rows.append([self._capture, *ms, done_ms, float(trusted)])

    def tick(self, now: float, verbose_line: Callable[[str], None] | None = None) -> None:
        """Once per loop turn: every `minute_s` the minute's percentiles (a
        line at info level: `nislam run -v`), and latency.csv's rows so far."""
        if self._minute_start is None:
            self._minute_start = now
            return
        if now - self._minute_start < self._minute_s:
            return
        self._close_minute(now, verbose_line)

    def finish(self) -> None:
        """The end of the run: the last (partial) minute's figures, the CSV's last rows."""
        if self._minute["done"].n:
            self._close_minute(time.monotonic(), lambda _line: None)
        self.flush_csv()

    def _close_minute(self, now: float, verbose_line: Callable[[str], None] | None) -> None:
        start = self._minute_start if self._minute_start is not None else now
        entry = {"t_s": now, "seconds": now - start,
                 "done_ms": percentiles(self._minute["done"]),
                 "written_ms": percentiles(self._minute["written"])}
        self.minutes.append(entry)
        if len(self.minutes) > 1440:  # a day of minutes at most
            del self.minutes[0]
        line = "latency " + minute_text(entry)
        (verbose_line or log.info)(line)
        self._minute = {"done": MsHistogram(), "written": MsHistogram()}
        self._minute_start = now
        self.flush_csv(final=False)

    # ------------------------------------------------------------ output threads
    def on_written(self, time_usec: int, t_written_s: float) -> None:
        """The MAVLink sender wrote the pose captured at `time_usec` (host µs)."""
        ms = max(0.0, (t_written_s - time_usec * 1e-6) * 1e3)
        self.written.add(ms)
        self._minute["written"].add(ms)
        self._push_recent(ms)
        one_way = self.one_way_s()
        if one_way is not None:
            self.arrival.add(ms + one_way * 1e3)
        if self._csv_file is not None:
            self._csv_written[int(time_usec)] = ms

    def on_stage(self, name: str, ms: float) -> None:
        """An output thread's own stage (MAVLink encode + send, zenoh encode + put)."""
        h = self.other.get(name)
        if h is None:
            with self._other_lock:
                h = self.other.setdefault(name, MsHistogram())
        h.add(ms)

    def _push_recent(self, ms: float) -> None:
        self._recent[self._recent_n % WINDOW] = ms
        self._recent_n += 1

    # ------------------------------------------------------------ results
    def latency(self) -> tuple[str, MsHistogram]:
        """The headline latency: capture -> written to the link when a MAVLink
        link wrote poses, capture -> tracker done otherwise."""
        return ("capture_to_written", self.written) if self.written.n else \
            ("capture_to_done", self.done)

    def recent(self) -> dict[str, Any]:
        """The status's figures: the last WINDOW frames' percentiles."""
        kind, _ = self.latency()
        return {"kind": kind, **percentiles_ms(  # a copy: the writer thread goes on
            self._recent[:min(self._recent_n, len(self._recent))].copy())}

    def rate_hz(self) -> float | None:
        if self.first_frame_at is None or self.last_frame_at is None or self.frames < 2:
            return None
        span = self.last_frame_at - self.first_frame_at
        return (self.frames - 1) / span if span > 0 else None

    def first_pose_s(self) -> float | None:
        """Service start (outputs opened, kernels ready, sensors starting) to
        the first trusted pose out of the tracker."""
        return None if self.first_pose_at is None else self.first_pose_at - self.service_start_s

    def status(self) -> dict[str, Any]:
        """What the zenoh status carries (its own thread, once a second)."""
        ts = self.timesync()
        return {"latency_ms": self.recent(), "timesync": ts,
                "delay_advice": delay_advice(self, ts, self.autopilot_timesyncs())}

    def run_fields(self, frames_offered: int, resets: int,
                   output_stats: dict[str, dict[str, Any]]) -> dict[str, Any]:
        """run.json's timing keys (see docs/service.md)."""
        kind, h = self.latency()
        with self._other_lock:
            other = dict(self.other)
        mav = output_stats.get("mavlink", {})
        ts = mav.get("timesync") or self.timesync()
        return {
            "frames_offered": frames_offered,
            "frames_processed": self.frames,
            "resets": resets,
            "untrusted_sent": int(mav.get("untrusted_sent", 0)),
            "rate_hz": self.rate_hz(),
            "health_good_share": self.good_frames / self.frames if self.frames else None,
            "latency_ms": {"kind": kind, **percentiles(h)},
            "latency_capture_to_done_ms": percentiles(self.done),
            "latency_capture_to_written_ms": percentiles(self.written),
            "latency_capture_to_arrival_ms": percentiles(self.arrival),
            "first_pose_s": self.first_pose_s(),
            "first_pose_since_process_start_s": (
                None if self.first_pose_at is None or self.process_start_s is None
                else self.first_pose_at - self.process_start_s),
            "stages_ms": {**{k: percentiles(v) for k, v in self.stages.items()},
                          "loop_frame": percentiles(self.frame_loop),
                          **{k: percentiles(v) for k, v in sorted(other.items())}},
            "stages_cpu_ms": {"tracker": percentiles(self.tracker_cpu),
                              "loop_frame": percentiles(self.frame_cpu)},
            "latency_minutes": list(self.minutes),
            "timesync": ts,
            "delay_advice": delay_advice(self, ts, mav.get("timesync_replies", 0) > 0),
        }

    def summary_lines(self, output_stats: dict[str, dict[str, Any]]) -> list[str]:
        kind, h = self.latency()
        lines = [f"latency     {_pct_text(percentiles(h))} ({kind.replace('_', ' ')})"]
        if self.arrival.n:
            lines.append(f"arrival     {_pct_text(percentiles(self.arrival))} (capture to "
                         "arrival: written + the link's one-way time from TIMESYNC)")
        mav = output_stats.get("mavlink", {})
        ts = mav.get("timesync") or self.timesync()
        if ts is not None:
            lines.append(f"timesync    autopilot clock {ts['offset_ms']:+.3f} ms from ours, "
                         f"round trip {ts['rtt_min_ms']:.2f} ms (least of {ts['samples']})")
        adv = delay_advice(self, ts, mav.get("timesync_replies", 0) > 0)
        if adv is not None:
            lines.append(f"delay       VISO_DELAY_MS {adv['VISO_DELAY_MS']}, EKF2_EV_DELAY "
                         f"{adv['EKF2_EV_DELAY']} (from capture to {adv['basis']}; "
                         "docs/autopilot.md)")
        tr = self.stages["tracker"]
        lines.append("loop        " + ", ".join(
            f"{k} {_ms(self.stages[k].percentile(50))}" for k in LOOP_STAGES)
            + f" (p50); tracker p99 {_ms(tr.percentile(99))}, frame p99 "
            f"{_ms(self.frame_loop.percentile(99))}; tracker CPU p50 "
            f"{_ms(self.tracker_cpu.percentile(50))}, p99 {_ms(self.tracker_cpu.percentile(99))}")
        return lines

    def flush_csv(self, final: bool = True) -> None:
        """latency.csv rows so far; a row whose pose the sender has not
        written yet waits for the next flush (unless final)."""
        f = self._csv_file
        if f is None:
            return
        rows, keep = self._csv_rows, []
        written = self._csv_written
        newest = rows[-1][0] if rows else 0.0
        for r in rows:
            key = int(round(r[0] * 1e6))
            w = written.pop(key, None)
            if w is None and not final and r[-1] and r[0] > newest - 0.5:
                keep.append(r)  # its pose may still be on its way to the link
                continue
            vals = [f"{key / 1e6:.6f}"] + [f"{v:.3f}" for v in r[1:-1]]  # time_usec's stamp
            vals.append("" if w is None else f"{w:.3f}")
            vals.append(str(int(r[-1])))
            f.write(",".join(vals) + "\n")
        self._csv_rows = keep
        if len(written) > 4 * WINDOW:  # poses of rows already written (or never seen)
            written.clear()
        f.flush()
        if final:
            f.close()
            self._csv_file = None


def delay_advice(t: LoopTiming, timesync: dict[str, Any] | None,
                 autopilot_timesyncs: bool = False) -> dict[str, Any] | None:
    """The EKF delay parameters from the measured capture-to-arrival latency
    (capture-to-written when no TIMESYNC answer told the link's time).

    ArduPilot maps our time_usec onto its clock by the least-delayed pose it
    has seen (JitterCorrection), then subtracts VISO_DELAY_MS: the pose is
    placed right when VISO_DELAY_MS is the least capture-to-arrival latency;
    the run's p1 stands for it (one early outlier does not set it). PX4 maps
    time_usec with its TIMESYNC (ours answers it), so EKF2_EV_DELAY is 0
    once PX4 has synchronised (we answered its requests); without that, it
    stamps poses on arrival and the delay is the typical (p50) latency."""
    h, basis = (t.arrival, "arrival") if t.arrival.n else (t.written, "written")
    if h.n == 0:
        return None
    p1, p50 = h.percentile(1), h.percentile(50)
    assert p1 is not None and p50 is not None
    return {
        "basis": basis,
        "latency_p1_ms": p1,
        "latency_p50_ms": p50,
        "VISO_DELAY_MS": int(min(250, round(p1))),
        "EKF2_EV_DELAY": 0 if autopilot_timesyncs else int(min(300, round(p50))),
        "EKF2_EV_DELAY_unsynchronised": int(min(300, round(p50))),
        "autopilot_timesyncs": autopilot_timesyncs,
        "link_one_way_ms": None if timesync is None else timesync["rtt_min_ms"] / 2,
    }


def attach_timing(outputs: Any, timing: LoopTiming, service_start_s: float) -> None:
    """Hook the outputs' threads into `timing`: the MAVLink sender reports
    each pose written and its TIMESYNC estimate, the zenoh publisher its
    encode-and-put times and carries `timing.status()` in its status."""
    timing.service_start_s = service_start_s
    for out in getattr(outputs, "outputs", (outputs,)):
        if hasattr(out, "on_written"):
            out.on_written = timing.on_written
            timing.one_way_s = out.one_way_s
            timing.timesync = out.timesync_estimate
            timing.autopilot_timesyncs = lambda o=out: o.stats()["timesync_replies"] > 0
        if hasattr(out, "on_stage"):
            out.on_stage = timing.on_stage
        if hasattr(out, "status_extra"):
            out.status_extra = timing.status


def _ms(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.1f}"


def _pct_text(p: dict[str, Any]) -> str:
    return (f"p50 {_ms(p['p50'])} / p95 {_ms(p['p95'])} / p99 {_ms(p['p99'])} ms "
            f"over {p['n']} frames")


def minute_text(entry: dict[str, Any]) -> str:
    d, w = entry["done_ms"], entry["written_ms"]
    text = f"capture->done {_pct_text(d)}"
    if w["n"]:
        text += f"; capture->written {_pct_text(w)}"
    return text
