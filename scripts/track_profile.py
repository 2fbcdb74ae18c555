"""Where NI-SLAM's per-frame time goes, frame by frame (a script, not a test).

    python scripts/track_profile.py SEQ_DIR [--max-frames N] [--slowest K]
                                    [--glibc-thresholds] [--json OUT]

Runs the tracker over SEQ_DIR (a recorded or rendered sequence, attitude as
`nislam replay` gives it) as the service does: track(), then finish_frame().
Each part of each frame is timed in the thread's CPU time (what the frame
cost, far less inflated than wall time by other jobs on the machine), and
counted: matches, re-used keys, new keys, residual fits, projections, FFT
responses; also the minor page faults and garbage collections during
track(). Prints the percentiles, each part's mean share and the K slowest
frames with what they did. `--glibc-thresholds` leaves glibc's allocator
as it is (the service fixes its thresholds: onboard/app/allocator.py).
Instruments by wrapping the tracker's functions: only for measuring.
"""

from __future__ import annotations

import argparse
import gc
import json
import resource
import sys
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from onboard.app.allocator import keep_freed_memory
from onboard.app.bench import pin_one_core, replay_attitude
from onboard.app.config import load_config
from onboard.fusion.registry import make_tracker
from onboard.nislam import calibration, correlation, keys
from onboard.nislam import tracker as tracker_mod
from onboard.nislam.tracker import NislamTracker
from sim_replay.tum import open_sequence

PARTS = [  # (owner, attribute, label)
    (NislamTracker, "_match", "match"),
    (NislamTracker, "_reuse", "reuse"),
    (NislamTracker, "_new_key_from", "new_key"),
    (NislamTracker, "_refine", "refine"),
    (NislamTracker, "_key_cloud", "key_cloud"),
    (tracker_mod, "make_cloud", "make_cloud"),
    (tracker_mod, "project", "project"),
    (tracker_mod, "whiten", "whiten"),
    (tracker_mod, "find_peak", "find_peak"),
    (tracker_mod, "depth_translation", "depth_translation"),
    (tracker_mod, "adaptive_resolution", "adaptive_res"),
    (correlation.KernelCorrelationFilter, "response", "response"),
    (correlation.KernelCorrelationFilter, "train", "filter_train"),
    (calibration.RotationResidual, "residual", "residual"),
    (keys.KeySlot, "hold", "slot_hold"),
]


def instrument(ms: dict[str, float], calls: dict[str, int]) -> None:
    def wrap(fn: Callable[..., Any], label: str) -> Callable[..., Any]:
        def timed(*a: Any, **k: Any) -> Any:
            t0 = time.thread_time_ns()
            try:
                return fn(*a, **k)
            finally:
                ms[label] += (time.thread_time_ns() - t0) * 1e-6
                calls[label] += 1
        return timed
    for owner, attr, label in PARTS:
        setattr(owner, attr, wrap(getattr(owner, attr), label))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("seq", type=Path)
    ap.add_argument("--config", type=Path)
    ap.add_argument("--max-frames", type=int)
    ap.add_argument("--slowest", type=int, default=12)
    ap.add_argument("--glibc-thresholds", action="store_true")
    ap.add_argument("--json", type=Path, help="every frame's figures")
    args = ap.parse_args()
    cfg = load_config(args.config)
    pin_one_core()
    if not args.glibc_thresholds:
        keep_freed_memory()
    seq = open_sequence(args.seq, cfg.replay.assoc_max_dt_s, cfg.replay.undistort,
                        cfg.replay.stamp_window_s)
    att, _ = replay_attitude(seq, cfg)
    ms: dict[str, float] = defaultdict(float)
    calls: dict[str, int] = defaultdict(int)
    instrument(ms, calls)
    tracker = make_tracker("nislam", seq.intrinsics, cfg)
    collections = [0]
    gc.callbacks.append(lambda phase, _info: collections.__setitem__(
        0, collections[0] + (phase == "start")))
    rows = []
    for i, frame in enumerate(seq.frames()):
        if args.max_frames is not None and i >= args.max_frames:
            break
        ms.clear()
        calls.clear()
        gc0, flt0 = collections[0], resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
        c0 = time.thread_time_ns()
        r = tracker.track(frame, att)
        c1 = time.thread_time_ns()
        flt = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - flt0
        pose_ms, pose_calls = dict(ms), dict(calls)
        ms.clear()
        calls.clear()
        tracker.finish_frame()
        c2 = time.thread_time_ns()
        rows.append({"frame": i, "track_ms": (c1 - c0) * 1e-6, "after_ms": (c2 - c1) * 1e-6,
                     "parts_ms": pose_ms, "calls": pose_calls, "after_parts_ms": dict(ms),
                     "page_faults": flt, "gc": collections[0] - gc0,
                     "new_key": bool(r.new_keyframe), "reused": bool(r.keyframe_reused),
                     "trusted": bool(r.trusted)})
    report(rows, args.slowest)
    if args.json is not None:
        args.json.write_text(json.dumps(rows))
    return 0


def report(rows: list[dict[str, Any]], slowest: int) -> None:
    t = np.array([r["track_ms"] for r in rows])
    a = np.array([r["after_ms"] for r in rows])
    f = np.array([r["page_faults"] for r in rows])
    print(f"{len(rows)} frames, CPU ms per track() p50 / p95 / p99 / max: "
          + " / ".join(f"{v:.2f}" for v in np.percentile(t, [50, 95, 99, 100])))
    print(f"after the pose (finish_frame): p50 {np.median(a):.2f}, max {a.max():.2f}; "
          f"page faults per track() p50 {np.median(f):.0f}; "
          f"collections during the frames {sum(r['gc'] for r in rows)}")
    labels = sorted({k for r in rows for k in r["parts_ms"]})
    for k in labels:
        v = np.array([r["parts_ms"].get(k, 0.0) for r in rows])
        n = np.array([r["calls"].get(k, 0) for r in rows])
        print(f"  {k:18s} mean {v.mean():6.2f} ms/frame  calls {int(n.sum()):5d}  "
              f"in {int((n > 0).sum())} frames")
    print(f"the {slowest} slowest frames (parts: CPU ms / calls):")
    for i in np.argsort(-t)[:slowest]:
        r = rows[i]
        kind = "re-used key" if r["reused"] else "new key" if r["new_key"] else \
            "lost" if not r["trusted"] else "matched"
        parts = ", ".join(f"{k} {v:.1f}/{r['calls'][k]}" for k, v in
                          sorted(r["parts_ms"].items(), key=lambda kv: -kv[1]) if v >= 0.3)
        print(f"  #{r['frame']:5d} {r['track_ms']:6.1f} ms ({kind}; +{r['after_ms']:.1f} after): {parts}")


if __name__ == "__main__":
    sys.exit(main())
