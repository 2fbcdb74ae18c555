"""The service under bad luck, fast and deterministic: a fake camera and a
scripted tracker drive the real loop (onboard.app.service.Service), so what
is asserted is the loop's own handling: a jumped pose is never written or
sent as trusted, a disk that fills up mid-run costs the last second with one
line and leaves readable files and no .tmp, an interrupted render never
blocks the next one, and sizes and durations typed too large are one line."""

from __future__ import annotations

import errno
import logging
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from fake_results import FakeCamera, NullRunner, ScriptedTracker

from onboard import NislamError
from onboard.app import run_files
from onboard.app.cli import main
from onboard.app.config import load_config
from onboard.app.service import Service
from onboard.app.sources import Sources
from onboard.core.attitude import AttitudeBuffer
from onboard.core.trajectory import parse_tum_lines

HZ = 30.0


def run_service(out: Path, frames: int, tracker: ScriptedTracker):
    cfg = load_config(None, {"service.stats_period_s": 3600.0})
    sources = Sources("fake", FakeCamera(frames), AttitudeBuffer(np.eye(3), 16, 0.1), NullRunner())
    svc = Service(cfg, sources, threading.Event(), out_dir=out,
                  tracker_factory=lambda *_: tracker)
    return svc, svc.run()


def poses_in(path: Path) -> np.ndarray:
    traj, bad = parse_tum_lines(path.read_text().splitlines())
    assert bad == 0  # whole lines only
    return np.column_stack([traj.t_s, traj.p_xyz_m])


def test_a_jump_the_motion_model_cannot_explain_is_not_written_as_trusted(tmp_path):
    # 90 frames at 30 Hz; from frame 40 the tracker is 0.49 m off.
    svc, result = run_service(tmp_path / "out", 90, ScriptedTracker(jump_at=40))
    m = result.metrics
    assert m["pose_gate"]["jumps"] == 1 and m["pose_gate"]["resets"] == 1
    assert m["frames_tracked"] == 90 - m["pose_gate"]["rejected"]
    # The jumped pose and the ones that confirmed it went out untrusted ...
    assert m["lost_reasons"] and all("step" in r for r in m["lost_reasons"])
    # ... and after it every pose carries the higher reset_counter.
    assert m["reset_counter"] == 1
    est = poses_in(tmp_path / "out" / "trajectory.tum")
    t_jump = 100.0 + 40 / HZ
    assert not np.any((est[:, 0] >= t_jump - 1e-6) & (est[:, 0] < t_jump + 2 / HZ - 1e-6))


def test_the_wait_for_the_first_frame_starts_after_the_kernels_compiled(tmp_path, monkeypatch):
    """A cold numba cache takes ~15 s on a fresh clone: not a camera that
    sends nothing. The health's first-frame wait counts from the loop's start."""
    from onboard.app import service as service_mod
    from onboard.app import warm

    # The service warms what `make venv` warms: every tracker's kernels, so a
    # fused tracker's (or a fallback's) FastORB does not load them from the
    # cache on its first frames (5 of `make run`'s frames were dropped so).
    assert service_mod.warm_up is warm.warm_up
    compiled_at: list[float] = []
    monkeypatch.setattr(service_mod, "warm_up", lambda: compiled_at.append(time.monotonic()))
    svc, result = run_service(tmp_path / "out", 30, ScriptedTracker())
    assert len(compiled_at) == 1 and svc.health.start_s >= compiled_at[0]
    assert result.metrics["frames_tracked"] == 30


class FillingDisk:
    """open() for trajectory.tum on a disk with room for `room` bytes."""

    def __init__(self, room: int) -> None:
        self.room = room

    def __call__(self, path, mode="r"):
        f = open(path, mode)
        disk = self

        class File:
            def write(self, text: str) -> int:
                if len(text) > disk.room:
                    f.write(text[: disk.room])  # the disk takes what fits
                    f.flush()
                    disk.room = 0
                    raise OSError(errno.ENOSPC, "No space left on device", str(path))
                disk.room -= len(text)
                return f.write(text)

            def flush(self) -> None:
                f.flush()

            def fileno(self) -> int:
                return f.fileno()

            def close(self) -> None:
                f.close()

        return File()


def test_a_full_disk_costs_the_last_second_with_one_line_and_no_tmp(tmp_path, monkeypatch, caplog):
    out = tmp_path / "out"
    monkeypatch.setattr(run_files, "_open_file", FillingDisk(room=3000))
    clock = iter(np.arange(0.0, 1000.0, 0.25))  # four poses per "second": flushed in batches
    real_init = run_files.LiveTrajectory.__init__

    def init(self, path, **kw):
        real_init(self, path, clock=lambda: next(clock), **kw)

    monkeypatch.setattr(run_files.LiveTrajectory, "__init__", init)

    def full(path, *a, **k):  # the end-of-run writes: the disk is still full
        tmp = Path(path).with_name(Path(path).name + ".tmp")
        tmp.write_text("half")
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp))

    monkeypatch.setattr("onboard.app.service.write_text_atomic", full)
    monkeypatch.setattr("onboard.app.service.write_tum", full)
    monkeypatch.setattr("onboard.app.service.write_run_json", lambda d, run: full(d / "run.json"))
    with caplog.at_level(logging.WARNING):
        svc, result = run_service(out, 120, ScriptedTracker())
    # Everything that reached the disk is a readable trajectory of whole lines.
    est = poses_in(out / "trajectory.tum")
    assert 20 < len(est) < 120
    assert np.allclose(est[:, 1], 0.1 * (est[:, 0] - 100.0), atol=1e-6)
    assert (out / "trajectory.tum").read_text().endswith("\n")
    assert not list(out.glob("*.tmp"))
    # One line when the recording stopped, one for the files of the end; no traceback.
    lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING
             and "No space left" in r.getMessage()]
    assert len(lines) == 2 and "trajectory.tum" in lines[0], lines
    assert all(n in lines[1] for n in ("config.toml", "metrics.json", "run.json")), lines
    assert not any(r.exc_info for r in caplog.records)
    summary = "\n".join(result.summary_lines())
    assert "recording stopped" in summary and f"{len(est)} poses" in summary
    assert result.metrics["frames"] == 120  # the run itself went on


def test_an_interrupted_render_never_blocks_the_next(tmp_path, monkeypatch):
    import sim_replay.sim as sim

    out = tmp_path / "flight"
    real_write = sim._write_png
    calls = []

    def interrupted(path, img):  # Ctrl-C while the frames are being written
        calls.append(path)
        if len(calls) == 5:
            raise KeyboardInterrupt
        real_write(path, img)

    monkeypatch.setattr(sim, "_write_png", interrupted)
    # `make run` renders with simulate() into results/run_sim_circle/flight;
    # coarse textures keep this test fast.
    opts = sim.SimOptions(seconds=0.5, width=64, height=48, texel_m=0.03)
    with pytest.raises(KeyboardInterrupt):
        sim.simulate("circle", out, opts, progress=False)
    # The unfinished folder is refused by a reader, in one line ...
    from sim_replay.tum import open_sequence

    with pytest.raises(NislamError, match="unfinished recording"):
        open_sequence(out)
    # ... and the next render (what `make run` does again) clears it and works.
    monkeypatch.setattr(sim, "_write_png", real_write)
    sim.simulate("circle", out, opts, progress=False)
    assert len(open_sequence(out)) == 15
    assert not (out / ".nislam-partial").exists()


@pytest.mark.parametrize("argv, expect", [
    (["sim", "circle", "--width", "100000"], "image size must be within"),
    (["sim", "circle", "--seconds", "1e9"], "--seconds must be in (0, 600]"),
    (["sim", "circle", "--camera-hz", "1e6"], "camera rate must be in"),
    (["sim", "circle", "--ahrs-hz", "1e7"], "AHRS rate must be in"),
    (["run", "--sim", "circle", "--seconds", "1e4"], "--seconds must be in (0, 600]"),
    (["run", "--sim", "circle", "--seconds", "1e8"], "--seconds must be in (0, 2592000]"),
    (["run", "--seconds", "1e9"], "--seconds must be in (0, 2592000]"),
    (["run", "--seconds", "nan"], "--seconds must be in"),
    (["record", "--out", "X", "--seconds", "1e12"], "--seconds must be in"),
    (["run", "--mavlink", "htp://what:ever:99999"], "mavlink.connect"),
    (["run", "--mavlink", "udpout:127.0.0.1:99999"], "port must be in 1..65535"),
])
def test_sizes_rates_durations_and_urls_out_of_bounds_are_one_line(argv, expect, tmp_path,
                                                                   capfd, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 1
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and expect in err[0], err
    assert not (tmp_path / "results").exists() or not any((tmp_path / "results").rglob("*.png"))


@pytest.mark.parametrize("key, value", [("mavlink.queue_frames", 10**9),
                                        ("oak.width", 100000), ("oak.fps", 1e6),
                                        ("service.start_grace_s", 1e9),
                                        ("ahrs.buffer_samples", 10**12)])
def test_config_sizes_rates_and_durations_have_upper_bounds(key, value):
    with pytest.raises(NislamError, match=key.replace(".", r"\.")):
        load_config(None, {key: value})


def test_the_summary_says_what_each_output_delivered(caplog):
    from onboard.app.delivery import DeliveryWatch, delivery_lines

    stats = {"mavlink": {"poses_sent": 590, "not_sent": 3, "link_up": True, "link_opens": 1,
                         "link_errors": 0, "received": 0, "heartbeats": 21,
                         "sent_by_type": {"ODOMETRY": 590, "HEARTBEAT": 21}},
             "zenoh": {"poses_published": 600, "keyframes_published": 12, "dropped_poses": 0,
                       "dropped_keyframes": 0, "errors": 0, "connected": True}}
    mav, zen = delivery_lines(stats)
    assert "590 poses sent" in mav and "link up" in mav and "nobody may be receiving" in mav
    assert "600 poses, 12 key frames published" in zen and "session open" in zen
    stats["mavlink"]["received"] = 40
    assert "40 messages back from the peer" in delivery_lines(stats)[0]

    class MavlinkOutput:  # what the watch reads of onboard.outputs.mavlink.MavlinkOutput
        class cfg:
            connect = "udpout:127.0.0.1:14550"

        def __init__(self) -> None:
            self.s = {"poses_sent": 0, "heartbeats": 1, "received": 0}

        def stats(self):
            return dict(self.s)

    class Group:
        outputs = [MavlinkOutput()]

    watch = DeliveryWatch(after_s=5.0)
    with caplog.at_level(logging.WARNING):
        for t in range(12):  # one stats period a second; nothing ever comes back
            Group.outputs[0].s["poses_sent"] += 30
            watch.check(Group, float(t))
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "udpout:127.0.0.1:14550" in lines[0]
    assert "nothing came back in 5 s: nobody may be receiving" in lines[0]
