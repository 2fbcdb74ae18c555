"""Per-frame latency and stage times of the service loop (onboard/app/latency.py)
on a scripted clock: what each stage and each latency is measured from and
to, the per-minute figures, latency.csv and the EKF delay advice."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from onboard.app import latency as latency_mod
from onboard.app.latency import LOOP_STAGES, LoopTiming, delay_advice


class Clock:
    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> Clock:
    c = Clock(100.0)
    monkeypatch.setattr(latency_mod.time, "monotonic", c)
    return c


def frame(t: LoopTiming, clock: Clock, capture: float, stage_ms: list[float], *,
          trusted: bool = True, good: bool = True) -> None:
    """One frame taken at clock.t; each LOOP_STAGES stage after "source" takes
    its stage_ms in turn."""
    t.frame_start(capture)
    for ms in stage_ms:
        clock.t += ms / 1e3
        t.lap()
    t.frame_end(trusted, good)


def test_stages_and_latencies_are_measured_from_capture(clock: Clock, tmp_path: Path) -> None:
    # A replay's stamps on another clock: the host reached stamp 5.0 at 99.95.
    t = LoopTiming(host_time_s=lambda s: s + 94.95, csv_path=tmp_path / "latency.csv")
    t.service_start_s = 99.0
    frame(t, clock, 5.0, [2.0, 10.0, 0.5, 1.0, 3.0], trusted=False, good=False)  # taken 50 ms late
    clock.t = 100.1
    frame(t, clock, 5.1, [0.0, 8.0, 0.2, 0.3, 0.0])  # capture at 100.05: taken 50 ms after it
    clock.t += 0.004
    assert t.written.n == 0
    t.one_way_s = lambda: 0.0005
    t.on_written(round(100.05e6), clock.t)  # written 4 ms after the loop finished
    assert t.stages["source"].n == 2
    assert t.stages["source"].percentile(50) == pytest.approx(50.0, abs=0.05)
    assert t.stages["tracker"].max_ms == pytest.approx(10.0)
    assert t.done.percentile(100) == pytest.approx(50 + 2 + 10, abs=0.05)  # capture -> done
    assert t.written.max_ms == pytest.approx(50 + 8 + 0.2 + 0.3 + 4)
    assert t.arrival.max_ms == pytest.approx(62.5 + 0.5)  # + the link's one-way time
    kind, h = t.latency()
    assert kind == "capture_to_written" and h is t.written
    # The first trusted pose: 1.158 s after the service started (its tracker end).
    assert t.first_pose_s() == pytest.approx(100.1 + 0.008 - 99.0)
    fields = t.run_fields(frames_offered=3, resets=0, output_stats={})
    assert fields["frames_processed"] == 2 and fields["health_good_share"] == 0.5
    assert fields["rate_hz"] == pytest.approx(1 / (100.1 - (100.0 + 0.0)), rel=1e-6)
    assert set(LOOP_STAGES) <= set(fields["stages_ms"]) and fields["untrusted_sent"] == 0
    t.flush_csv()
    rows = list(csv.DictReader((tmp_path / "latency.csv").open()))
    assert [r["trusted"] for r in rows] == ["0", "1"]
    assert rows[0]["written_ms"] == ""  # no pose sent for it
    assert float(rows[1]["written_ms"]) == pytest.approx(62.5, abs=1e-3)
    assert float(rows[1]["done_ms"]) == pytest.approx(58.0, abs=1e-3)


def test_a_pose_written_after_a_periodic_flush_still_reaches_its_row(clock: Clock,
                                                                      tmp_path: Path) -> None:
    t = LoopTiming(csv_path=tmp_path / "latency.csv")
    frame(t, clock, 99.99, [0.0, 5.0, 0.1, 0.1, 0.0])
    t.flush_csv(final=False)  # its pose is not written yet: the row waits
    t.on_written(round(99.99e6), clock.t + 0.002)
    t.flush_csv()
    rows = list(csv.DictReader((tmp_path / "latency.csv").open()))
    assert len(rows) == 1 and float(rows[0]["written_ms"]) == pytest.approx(17.2, abs=1e-3)


def test_cpu_time_is_the_loop_threads_own(clock: Clock, monkeypatch: pytest.MonkeyPatch) -> None:
    """A frame whose track() takes 12 ms of wall time but only 3 ms of the
    thread's CPU (the machine's other jobs had the core the rest): run.json's
    stages_cpu_ms says 3 ms for the tracker, the frame's CPU counts every
    stage's, and the wall-time stages are unchanged."""
    cpu = Clock(7.0)
    monkeypatch.setattr(latency_mod.time, "thread_time", cpu)
    t = LoopTiming()
    t.frame_start(clock.t - 0.040)
    for wall_ms, cpu_ms in [(1.0, 0.5), (12.0, 3.0), (0.2, 0.2), (0.5, 0.5), (2.0, 1.0)]:
        clock.t += wall_ms / 1e3
        cpu.t += cpu_ms / 1e3
        t.lap()
    t.frame_end(True, True)
    fields = t.run_fields(frames_offered=1, resets=0, output_stats={})
    assert fields["stages_cpu_ms"]["tracker"]["p50"] == pytest.approx(3.0, abs=0.05)
    assert fields["stages_cpu_ms"]["loop_frame"]["max"] == pytest.approx(5.2)
    assert fields["stages_ms"]["tracker"]["max"] == pytest.approx(12.0)
    (loop,) = [line for line in t.summary_lines({}) if line.startswith("loop")]
    assert "tracker p99 12.0" in loop and "tracker CPU p50 3.0, p99 3.0" in loop


def test_minute_figures_and_the_verbose_line(clock: Clock) -> None:
    t = LoopTiming(minute_s=60.0)
    lines: list[str] = []
    t.tick(clock.t, lines.append)
    for i in range(30):
        frame(t, clock, clock.t - 0.020, [0.0, 5.0 + i % 3, 0.1, 0.1, 0.0])
        clock.t += 1.0
        t.tick(clock.t, lines.append)
    assert not t.minutes
    clock.t += 31.0
    t.tick(clock.t, lines.append)
    assert len(t.minutes) == 1 and t.minutes[0]["done_ms"]["n"] == 30
    assert t.minutes[0]["written_ms"]["n"] == 0
    assert len(lines) == 1 and lines[0].startswith("latency capture->done p50 ")
    frame(t, clock, clock.t - 0.020, [0.0, 5.0, 0.1, 0.1, 0.0])
    assert t.done.n == 31  # the run's histogram goes on; the minute's starts again


def test_delay_advice(clock: Clock) -> None:
    t = LoopTiming()
    assert delay_advice(t, None) is None  # nothing written: no advice
    for ms in [30.0] + [45.0] * 98 + [200.0]:
        t.arrival.add(ms)
        t.written.add(ms - 1)
    adv = delay_advice(t, {"rtt_min_ms": 2.0})
    assert adv is not None and adv["basis"] == "arrival"
    # ArduPilot: the least latency (p1 of the run); PX4 without timesync: p50.
    assert adv["VISO_DELAY_MS"] == 45 and adv["EKF2_EV_DELAY"] == 45
    assert delay_advice(t, None, autopilot_timesyncs=True)["EKF2_EV_DELAY"] == 0
    t.arrival = latency_mod.MsHistogram()
    assert delay_advice(t, None)["basis"] == "written"
