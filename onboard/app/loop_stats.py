"""The service loop's statistics: per-frame times in constant memory, counters,
the periodic statistics line and the run's summary.
"""

from __future__ import annotations

import collections
import json
import os
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from onboard.fusion.switching import SwitchingTracker


def percentiles_ms(values: Any) -> dict[str, float | None]:
    """p50 / p95 / p99 of a sample of milliseconds; None each when it is empty."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        return {"p50": None, "p95": None, "p99": None}
    p = np.percentile(v, (50, 95, 99))
    return {"p50": float(p[0]), "p95": float(p[1]), "p99": float(p[2])}


class MsHistogram:
    """Per-frame times in fixed 0.05 ms bins up to 2 s: percentiles of a run
    of any length in constant memory (a service runs for hours)."""

    BIN_MS = 0.05
    MAX_MS = 2000.0

    def __init__(self) -> None:
        self.counts = np.zeros(int(self.MAX_MS / self.BIN_MS) + 1, dtype=np.int64)
        self.n = 0
        self.max_ms = 0.0

    def add(self, ms: float) -> None:
        self.counts[min(int(ms / self.BIN_MS), len(self.counts) - 1)] += 1
        self.n += 1
        self.max_ms = max(self.max_ms, ms)

    def percentile(self, q: float) -> float | None:
        """The q-th percentile to a bin's width (bin centres); None when empty."""
        if self.n == 0:
            return None
        rank = q / 100.0 * (self.n - 1)
        i = int(np.searchsorted(np.cumsum(self.counts), rank + 1))
        return min((i + 0.5) * self.BIN_MS, self.max_ms)

    def stats(self) -> dict[str, float | None]:
        median = self.percentile(50)
        return {
            "frame_ms_median": median,
            "frame_ms_p95": self.percentile(95),
            "frame_ms_p99": self.percentile(99),
            "frame_ms_max": self.max_ms if self.n else None,
        }


@dataclass
class LoopStats:
    """Counters of the loop; per-frame times of the run (histogram) and of the
    current statistics period. Memory stays constant however long it runs."""

    frames: int = 0
    tracked: int = 0
    keyframes: int = 0
    resets: int = 0
    loop_turns: int = 0
    idle_turns: int = 0
    frame_ms: MsHistogram = field(default_factory=MsHistogram)  # track + publish
    period_ms: list[float] = field(default_factory=list)
    period_frames: int = 0
    period_start_s: float = 0.0
    last_psr: float = float("nan")
    period_att_lead_ms: float = float("inf")  # least AHRS lead over a frame this period
    lost_reasons: collections.Counter = field(default_factory=collections.Counter)
    health_changes: int = 0
    periods: deque[dict[str, Any]] = field(  # one per stats line, the last hour at 5 s
        default_factory=lambda: deque(maxlen=720))


@dataclass
class RunResult:
    metrics: dict[str, Any]
    out_dir: Path | None

    def summary_lines(self) -> list[str]:
        m = self.metrics
        lines = [
            f"source      {m['source']}  (tracker {m['tracker']}"
            f"{', fallback ' + m['fallback_tracker'] if m['fallback_tracker'] else ''})",
            f"ran         {m['seconds']:.1f} s, {m['frames']} frames tracked at "
            f"{m['frame_hz']:.1f} Hz, dropped {m['frames_dropped']}",
            f"tracked     {m['frames_tracked']} trusted, {m['frames'] - m['frames_tracked']} "
            f"untrusted; key frames {m['keyframes']}; resets {m['reset_counter']}; "
            f"tracker switches {m['tracker_switches']}",
            f"per frame   median {_ms(m['frame_ms_median'])}, p95 {_ms(m['frame_ms_p95'])}, "
            f"max {_ms(m['frame_ms_max'])} (track + publish)",
            f"health      {m['health']} at the end; {m['health_changes']} changes",
            *m.get("latency_lines", []),  # onboard/app/latency.py
        ]
        if m.get("ate_rmse_m") is not None:
            lines.append(f"ATE RMSE    {m['ate_rmse_m']:.4f} m over {m['frames_evaluated']} "
                         f"frames (SE(3)-aligned); RPE {_rpe(m)}")
        elif m.get("evaluation_note"):
            lines.append(f"ATE         not computed: {m['evaluation_note']}")
        lines += m.get("output_notes", [])  # what each output delivered; files not written
        if self.out_dir is not None:
            lines.append(f"output      {self.out_dir}")
        return lines


def _ms(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.1f} ms"


def _rpe(m: dict[str, Any]) -> str:
    v = m.get("rpe_trans_rmse_m")
    return "n/a" if v is None else f"{v:.4f} m / {m['rpe_rot_rmse_deg']:.2f} deg (1 s)"


def stats_line(p: dict[str, Any], tracker: SwitchingTracker | None) -> str:
    name = "-" if tracker is None else tracker.active_name
    ms = "n/a" if p["ms_median"] is None else f"{p['ms_median']:.1f} ms (p95 {p['ms_p95']:.1f})"
    psr = "n/a" if not np.isfinite(p["psr"]) else f"{p['psr']:.0f}"
    return (f"{p['health']:<8} {p['hz']:5.1f} Hz  {ms}  dropped {p['dropped']}  "
            f"PSR {psr}  key frames {p['keyframes']}  resets {p['resets']}  "
            f"offset {p['attitude_offset_ms']:+.0f} ms  AHRS lead {_lead(p)}  [{name}]")


def _lead(p: dict[str, Any]) -> str:
    lead = p["attitude_lead_ms_min"]
    return "n/a" if not np.isfinite(lead) else f"{lead:+.0f} ms"


def jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [jsonable(x) for x in v]
    if isinstance(v, (float, np.floating)):
        return float(v) if np.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


RUN_FILE = "run.json"


def write_run_json(out_dir: Path, run: dict[str, Any]) -> Path:
    """`<out>/run.json`: what the run did, for scripts (one JSON object,
    written whole). Keys so far: keyframes_published (distinct key-frame ids
    the zenoh output published and holds for late joiners; null without
    zenoh), keyframe_crc32 (id -> CRC-32 of its message), outputs (each
    output's counters)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / RUN_FILE
    tmp = path.with_name(RUN_FILE + ".tmp")  # then rename: never half a file
    tmp.write_text(json.dumps(jsonable(run), indent=2, allow_nan=False) + "\n")
    os.replace(tmp, path)
    return path
