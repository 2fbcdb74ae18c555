"""The onboard health state machine (onboard/app/health.py), step by step."""

from __future__ import annotations

import dataclasses

from fake_results import track_result

from onboard.app.health import HealthMonitor, HealthThresholds
from onboard.core.messages import Health, TrackState

TH = HealthThresholds(frame_timeout_s=0.5, degraded_gap_s=0.2, degraded_quality=20,
                      start_grace_s=10.0, recover_s=0.0)  # no dwell: each rule on its own
TH_DWELL = dataclasses.replace(TH, recover_s=1.0)


def test_starting_then_tracking_and_the_first_report_is_announced() -> None:
    h = HealthMonitor(TH, start_s=0.0)
    first = h.on_idle(1.0)
    assert (first.state, first.changed) == (Health.STARTING, True)
    assert h.on_idle(2.0).changed is False
    r = h.on_frame(2.1, track_result(0.0, trusted=False, state=TrackState.INITIALIZING,
                                     lost_reason="no attitude"), None)
    assert r.state is Health.STARTING and "no attitude" in r.reason
    r = h.on_frame(2.13, track_result(0.03, quality=60), None)
    assert (r.state, r.changed) == (Health.TRACKING, True)


def test_no_camera_at_start_is_lost_after_the_grace_period() -> None:
    h = HealthMonitor(TH, start_s=0.0)
    assert h.on_idle(9.9).state is Health.STARTING
    r = h.on_idle(10.1)
    assert r.state is Health.LOST and "no frames from the camera" in r.reason


def test_frames_stopping_is_lost_and_coming_back_is_tracking() -> None:
    h = HealthMonitor(TH, start_s=0.0)
    h.on_frame(1.0, track_result(1.0), None)
    assert h.on_idle(1.4).state is Health.TRACKING  # within frame_timeout_s
    r = h.on_idle(1.6)
    assert r.state is Health.LOST and "no frames for 0.6 s" == r.reason
    # The first frame after the silence arrives after a long gap: degraded, then fine.
    r = h.on_frame(2.0, track_result(2.0), None)
    assert r.state is Health.DEGRADED and "frame gap" in r.reason
    assert h.on_frame(2.033, track_result(2.033), None).state is Health.TRACKING


def test_untrusted_after_a_pose_is_lost() -> None:
    h = HealthMonitor(TH, start_s=0.0)
    h.on_frame(1.0, track_result(1.0), None)
    r = h.on_frame(1.03, track_result(1.03, trusted=False, lost_reason="correlation peak too weak"),
                   None)
    assert (r.state, r.reason) == (Health.LOST, "correlation peak too weak")


def test_low_quality_and_fallback_are_degraded_with_hysteresis() -> None:
    h = HealthMonitor(TH, start_s=0.0)
    t = 1.0
    states = []
    for q in (60, 15, 22, 26, 60):
        states.append(h.on_frame(t, track_result(t, quality=q), None).state)
        t += 0.033
    assert states == [Health.TRACKING, Health.DEGRADED, Health.DEGRADED, Health.TRACKING,
                      Health.TRACKING]
    r = h.on_frame(t, track_result(t, quality=80), "fastorb")
    assert r.state is Health.DEGRADED and "fallback tracker fastorb" in r.reason


def test_recovery_waits_recover_s_without_a_problem() -> None:
    """A camera that stutters (a frame gap every 0.5 s) keeps the state
    degraded instead of flapping it; it turns tracking only once the gaps
    have stayed away for recover_s, and a lost spell ends the same way."""
    h = HealthMonitor(TH_DWELL, start_s=0.0)
    assert h.on_frame(1.0, track_result(1.0), None).state is Health.TRACKING
    t, t_gap, states = 1.0, 0.0, []
    for k in range(60):  # 30 Hz for 2 s, a 0.3 s gap before every 15th frame
        if k % 15 == 14:
            t, t_gap = t + 0.3, t + 0.3
        else:
            t += 0.033
        states.append(h.on_frame(t, track_result(t), None))
    assert all(r.state is Health.DEGRADED for r in states[14:]), [r.state for r in states]
    assert "recovering (frame gap 0.30 s)" in {r.reason for r in states}
    assert sum(r.changed for r in states) == 1  # one change, not one per gap
    while t < t_gap + 1.5:  # then no more gaps
        t += 0.033
        r = h.on_frame(t, track_result(t), None)
        assert r.state is (Health.TRACKING if t - t_gap >= 1.0 else Health.DEGRADED), t - t_gap
    # Lost (an untrusted result), then trusted again: recovering for 1 s.
    t += 0.033
    assert h.on_frame(t, track_result(t, trusted=False, lost_reason="no attitude"),
                      None).state is Health.LOST
    t_lost = t
    t += 0.033
    r = h.on_frame(t, track_result(t), None)
    assert (r.state, r.reason) == (Health.DEGRADED, "recovering (no attitude)")
    while t < t_lost + 1.2:
        t += 0.033
        r = h.on_frame(t, track_result(t), None)
    assert r.state is Health.TRACKING
