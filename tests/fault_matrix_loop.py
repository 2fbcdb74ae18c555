"""The service-loop rows of the fault matrix (tests/fault_matrix.py): a
paced fake camera and a scripted tracker behind the real Service, so what is
measured is the loop's own handling (the pose gate, the health, the files it
writes); and a corrupt configuration at a (re)start."""

from __future__ import annotations

import errno
import threading
import time
from pathlib import Path

import numpy as np
from fake_results import NullRunner, ScriptedTracker
from fault_matrix import WAIT_S, Lines, Row, _has

from onboard.core.attitude import AttitudeBuffer


class PacedCamera:
    """Frames at `hz` in real time; none while `stalled`."""

    def __init__(self, seconds: float, hz: float = 30.0) -> None:
        from onboard.core.camera import CameraModel

        self.hz, self.n = hz, int(seconds * hz)
        self.t0 = float("inf")  # the flight starts at the loop's first take()
        self.k = 0
        self.stalled_until = 0.0
        self.model = CameraModel(100.0, 100.0, 32.0, 24.0, 64, 48, 1000.0)

    def wait_camera(self, timeout_s: float):
        return self.model

    def take(self, after_seq: int = 0, timeout_s: float = 0.0):
        from onboard.core.messages import RgbdFrame

        if self.t0 == float("inf"):
            self.t0 = time.monotonic()
        due = self.t0 + (self.k + 1) / self.hz
        now = time.monotonic()
        if now < due or now < self.stalled_until or self.k >= self.n:
            time.sleep(min(timeout_s, max(0.0, due - now), 0.02))
            return None
        # A stall loses the frames it covered, as a starved camera thread does.
        self.k = max(self.k + 1, int((now - self.t0) * self.hz))
        t = 100.0 + self.k / self.hz
        return self.k, RgbdFrame(t, np.zeros((48, 64, 3), np.uint8), np.ones((48, 64), np.float32))

    @property
    def exhausted(self) -> bool:
        return self.k >= self.n


def service_fault(fault: str, lines: Lines, tmp: Path) -> Row:
    from onboard.app import run_files
    from onboard.app.config import load_config
    from onboard.app.service import Service
    from onboard.app.sources import Sources
    from onboard.core.trajectory import parse_tum_lines

    seconds = 5.0
    cam = PacedCamera(seconds)
    tracker = ScriptedTracker(jump_m=0.0)
    cfg = load_config(None, {"service.stats_period_s": 3600.0, "service.recover_s": 0.5,
                             "service.degraded_gap_s": 0.2, "service.frame_timeout_s": 2.0})
    out = tmp / f"run_{fault.replace(' ', '_')}"
    src = Sources("paced", cam, AttitudeBuffer(np.eye(3), 16, 0.1), NullRunner())
    svc = Service(cfg, src, threading.Event(), out_dir=out, tracker_factory=lambda *_: tracker)
    real_open = run_files._open_file
    disk = {"full": False}

    class Disk:  # a disk that fills up when told
        def __init__(self, f) -> None:
            self.f = f

        def write(self, text: str) -> int:
            if disk["full"]:
                raise OSError(errno.ENOSPC, "No space left on device")
            return self.f.write(text)

        def __getattr__(self, name):
            return getattr(self.f, name)

    run_files._open_file = lambda p, m="r": Disk(real_open(p, m))
    th = threading.Thread(target=svc.run, daemon=True)
    th.start()
    try:
        while svc.stats.frames < 30 and th.is_alive():
            time.sleep(0.01)
        t_inject = time.monotonic()
        if fault == "pose jump after a gap":
            cam.stalled_until = t_inject + 0.33
            tracker.jump_at_s = 100.0 + (t_inject + 0.3 - cam.t0)
            tracker.jump_m = 0.49
            t_warn = lines.wait(_has("pose jump the motion model cannot explain"), t_inject)
            detector = "pose gate: the 0.33 s gap, then 2 poses withheld and checked"
        elif fault == "frames late (CPU starved)":
            cam.stalled_until = t_inject + 0.5
            t_warn = lines.wait(_has("health: degraded", "frame gap"), t_inject)
            detector = "degraded_gap_s 0.2 s (at the next frame)"
        elif fault == "wall-clock jump":
            real_time = time.time
            time.time = lambda: real_time() + 3600.0  # NTP steps the clock an hour
            try:
                lost_before = sum(svc.stats.lost_reasons.values())
                changes = svc.stats.health_changes
                time.sleep(1.0)  # the fault's duration: a second with the clock an hour ahead
                passed_wall = sum(svc.stats.lost_reasons.values()) - lost_before
                unchanged = svc.stats.health_changes == changes
            finally:
                time.time = real_time
            t_warn = float("nan")  # nothing to warn about: nothing reads the wall clock
            detector = "none needed: every stamp is CLOCK_MONOTONIC"
        else:  # disk full while recording
            disk["full"] = True
            t_warn = lines.wait(_has("trajectory.tum", "No space left"), t_inject)
            detector = "the next flush (every 1 s)"
        t_clear = time.monotonic() if fault != "pose jump after a gap" else t_warn
        disk["full"] = False
        deadline = time.monotonic() + WAIT_S
        while svc.health.report.state.value != "tracking" and time.monotonic() < deadline \
                and th.is_alive():
            time.sleep(0.01)
        t_rec = time.monotonic() if th.is_alive() else float("inf")
        th.join(WAIT_S)
    finally:
        run_files._open_file = real_open
    traj, bad = parse_tum_lines((out / "trajectory.tum").read_text().splitlines())
    passed = 0
    lost = "none"
    if fault == "pose jump after a gap":
        gate = svc.gate.stats
        off = traj.p_xyz_m[:, 0] > 0.1 * (traj.t_s - 100.0) + 0.2  # carries the 0.49 m jump
        # The jumped poses written as trusted before the gate's verdict: none
        # may be (after it they carry the reset).
        passed = int(off.sum()) if gate.jumps != 1 else 0
        note = (f"{gate.rejected} poses withheld, then reset_counter +{gate.resets}; "
                f"{int(off.sum())} later poses written in the new segment")
    elif fault == "disk full while recording":
        written = len(traj.t_s)
        lost = "none" if bad == 0 and written == svc.stats.tracked else \
            f"{svc.stats.tracked - written} poses" + ("" if bad == 0 else ", UNREADABLE")
        note = ("trajectory.tum cut back to its last whole line, readable; rewritten whole "
                "at the end once the disk had room")
    elif fault == "wall-clock jump":
        passed = passed_wall
        note = ("+1 h: no frame untrusted, health " +
                ("unchanged" if unchanged else "CHANGED"))
    else:
        note = f"{svc.stats.frames} frames, health recovered after recover_s 0.5 s"
    return Row(fault, detector, t_warn - t_inject, max(t_rec - t_clear, 0.0), passed, lost, note)


def config_fault(lines: Lines, tmp: Path) -> Row:
    """A corrupt configuration: the service reads it once, at start (there
    is no reload), so the fault is a bad file at a (re)start."""
    from onboard import NislamError
    from onboard.app.config import load_config

    bad = tmp / "corrupt.toml"
    bad.write_text('[service]\npoll_s = 0.05\n[mavlink\nconnect = "udpout:127.0.0.1:1"\n')
    t0 = time.monotonic()
    try:
        load_config(bad)
        raise AssertionError("a corrupt config was accepted")
    except NislamError as e:
        t_warn = time.monotonic()
        one_line = "\n" not in str(e).strip()
    return Row("corrupt config (at a restart)", "TOML parse and validation at start",
               t_warn - t0, 0.0, 0 if one_line else 1, "none",
               "one line, exit 1; no reload: a running service keeps the config it read")
