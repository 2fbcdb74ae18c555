"""The back end (FastORB's local BA) runs in the loop's idle time: the
wrappers forward `backend_step()` to the tracker doing the work, and the
service calls it between frames without starving them (issue 18, item 5)."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from fake_results import track_result

from onboard.app.config import load_config
from onboard.app.service import Service
from onboard.app.sources import replay_sources
from onboard.core.camera import CameraIntrinsics
from onboard.core.messages import TrackResult
from onboard.fusion.fused import FusedTracker
from onboard.fusion.switching import NO_ATTITUDE, SwitchingTracker
from sim_replay.sim import SimOptions, simulate


class Stub:
    """A tracker with `work` back-end units queued; lost without attitude
    when `no_attitude` (so SwitchingTracker starts its fallback)."""

    def __init__(self, name: str, work: int, no_attitude: bool = False) -> None:
        self.name, self.work, self.no_attitude, self.steps = name, work, no_attitude, 0

    def track(self, frame: Any, attitude: Any) -> TrackResult:
        return track_result(frame.t_s, trusted=False,
                            lost_reason=NO_ATTITUDE if self.no_attitude else "test")

    def backend_step(self) -> bool:
        if self.work == 0:
            return False
        self.work -= 1
        self.steps += 1
        return True

    def finish(self) -> None:
        return None


class NoBackEnd:
    name = "nislam"


class Frame:
    t_s = 1.0


def test_switching_forwards_to_the_active_tracker() -> None:
    primary = Stub("nislam", work=2, no_attitude=True)
    fallback = Stub("fastorb", work=3)
    sw = SwitchingTracker(primary, lambda: fallback)
    assert sw.backend_step() and sw.backend_step() and not sw.backend_step()
    assert primary.steps == 2
    sw.track(Frame(), None)  # no attitude: the fallback takes over
    assert sw.fallback is fallback
    assert [sw.backend_step() for _ in range(4)] == [True, True, True, False]
    assert fallback.steps == 3
    assert not SwitchingTracker(NoBackEnd(), None).backend_step()


def test_fused_forwards_to_the_part_with_work() -> None:
    nislam, fastorb = Stub("nislam", work=0), Stub("fastorb", work=2)
    fused = FusedTracker([nislam, fastorb])
    assert [fused.backend_step() for _ in range(3)] == [True, True, False]
    assert fastorb.steps == 2


class BusyBackEnd:
    """A tracker that tracks at once (`inner`: a stub) and whose back end
    always has a 3 ms unit of work."""

    def __init__(self, inner: Any) -> None:
        self.inner, self.name = inner, "busy"
        self.frames = 0
        self.steps = 0
        self.steps_at_frame: list[int] = []

    def track(self, frame: Any, attitude: Any) -> Any:
        self.frames += 1
        self.steps_at_frame.append(self.steps)
        return self.inner.track(frame, attitude)

    def backend_step(self) -> bool:
        time.sleep(0.003)  # the work itself, not synchronisation
        self.steps += 1
        return True

    def finish(self) -> Any:
        return self.inner.finish()


def test_service_runs_the_back_end_between_frames(tmp_path: Path) -> None:
    """Back-end units run in the gaps between frames (30 Hz: about ten 3 ms
    units fit), and a back end that always has work does not starve tracking:
    the frames are taken as they come, not dropped."""
    flight = tmp_path / "circle"
    simulate("circle", flight, SimOptions(seconds=1.0, width=160, height=120), progress=False)
    cfg = load_config()
    sources, cfg = replay_sources(cfg, flight)
    holder: dict[str, BusyBackEnd] = {}

    def factory(name: str, intr: CameraIntrinsics, c: Any) -> BusyBackEnd:
        holder["t"] = BusyBackEnd(Stub(name, work=0))
        return holder["t"]

    service = Service(cfg, sources, threading.Event(), tracker_factory=factory)
    service.run()
    tracker = holder["t"]
    gaps = np.diff(tracker.steps_at_frame)
    print(f"{tracker.frames} frames, {tracker.steps} back-end units, per gap median "
          f"{np.median(gaps):.0f}; dropped {sources.camera.slot.stats.dropped}")
    # A loop that ran the back end instead of taking frames would drop them.
    # (A few drop on a loaded machine with no back end at all.)
    assert sources.camera.slot.stats.dropped <= 0.2 * tracker.frames
    assert np.mean(gaps > 0) >= 0.5  # the idle time went to the back end


def test_local_ba_switches() -> None:
    """--local-ba / --no-local-ba set [fastorb] local_ba either way (to
    measure what the back end gains); neither leaves the config's value."""
    from onboard.app.cli import build_parser
    from onboard.app.cli_tracking import _overrides

    parser = build_parser()
    for flags, want in (([], None), (["--local-ba"], True), (["--no-local-ba"], False)):
        for cmd in ("replay", "bench"):
            args = parser.parse_args([cmd, "SEQ", *flags] if cmd == "replay" else [cmd, *flags])
            assert _overrides(args).get("fastorb.local_ba") == want, (cmd, flags)
