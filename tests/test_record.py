"""Replay drivers and `nislam record`: a recording made through the driver
interfaces reproduces the original sequence; a killed recorder leaves a
readable one; the live path runs on stand-in hardware."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.recorder import SequenceWriter, record
from onboard import NislamError
from onboard.config import load_config
from sim_replay.attitude import AttitudeErrorModel, attitude_for_replay
from sim_replay.sources import FRAME_DELIVERY_S, PREROLL_S, ReplayClock, open_replay
from sim_replay.tum import open_sequence

os.environ["DEPTHAI_PROTOCOL"] = "usb"

WAIT_S = 60.0
FIXTURE = "fixtures/tum_fr3_office_16frames"


def make_sequence(path: Path, n_frames: int = 60, fps: float = 30.0, w: int = 80, h: int = 60,
                  t0: float = 1000.0) -> Path:
    """A small TUM-layout sequence: textured colour, millimetre depth, a 100 Hz
    attitude.txt (a yaw/pitch sweep) and camera.toml with a forward mount."""
    rng = np.random.default_rng(7)
    (path / "rgb").mkdir(parents=True)
    (path / "depth").mkdir()
    rgb_lines, depth_lines = [], []
    for i in range(n_frames):
        t = t0 + i / fps
        name = f"{t:.6f}.png"
        colour = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        depth = rng.integers(300, 5000, (h, w), dtype=np.uint16)
        depth[:3] = 0  # invalid pixels stay invalid
        cv2.imwrite(str(path / "rgb" / name), colour)
        cv2.imwrite(str(path / "depth" / name), depth)
        rgb_lines.append(f"{t:.6f} rgb/{name}")
        depth_lines.append(f"{t + 0.001:.6f} depth/{name}")
    (path / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (path / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    t_att = np.arange(t0 - 0.5, t0 + n_frames / fps + 0.5, 0.01)
    q = Rotation.from_euler("zy", np.stack([np.sin(t_att - t0), 0.3 * np.cos(t_att - t0)], 1)
                            ).as_quat()
    (path / "attitude.txt").write_text("".join(
        f"{t:.6f} {a:.9f} {b:.9f} {c:.9f} {d:.9f}\n" for t, (a, b, c, d) in zip(t_att, q)))
    (path / "camera.toml").write_text(
        f"fx = 70.0\nfy = 71.0\ncx = 40.0\ncy = 30.0\nwidth = {w}\nheight = {h}\n"
        "depth_scale = 1000.0\nq_B_C_xyzw = [0.5, 0.5, 0.5, 0.5]\n")
    return path


def assert_same_frames(original: Path, recorded: Path, at_least: int) -> int:
    a, b = open_sequence(original), open_sequence(recorded)
    by_t = {round(f.t_s, 6): f for f in a.frames()}
    n = 0
    for f in b.frames():
        o = by_t[round(f.t_s, 6)]
        assert np.array_equal(o.bgr, f.bgr)
        assert np.array_equal(o.depth_m, f.depth_m)
        n += 1
    assert n >= at_least and b.skipped.unreadable_files == 0 and b.skipped.missing_files == 0
    return n


def assert_complete(result, n_frames: int) -> None:
    """Every source frame was recorded, or counted as dropped: a newest-frame
    slot drops a frame the recorder could not take within one frame period,
    which only a badly overloaded machine causes (none in normal runs)."""
    assert result.frames + result.frames_dropped == n_frames, result
    assert result.frames >= n_frames - 2, result


def attitude_error_deg(original: Path, recorded: Path) -> float:
    """Largest angle between the two sequences' R_W_C at the recorded frames."""
    a, b = open_sequence(original), open_sequence(recorded)
    att_a, _ = attitude_for_replay(a, AttitudeErrorModel())
    att_b, _ = attitude_for_replay(b, AttitudeErrorModel())
    worst, checked = 0.0, 0
    for t in b.frame_times_s:
        ra, rb = att_a.rotation_at(float(t)), att_b.rotation_at(float(t))
        if ra is None:
            continue
        assert rb is not None, f"recording lost the attitude at {t}"
        worst = max(worst, float(np.degrees(Rotation.from_matrix(ra.T @ rb).magnitude())))
        checked += 1
    assert checked > 0
    return worst


# --------------------------------------------------------------------------- replay drivers


def test_replay_clock_paces_real_time() -> None:
    now = [0]
    clock = ReplayClock(100.0, speed=2.0, mono_ns=lambda: now[0])
    assert clock.now_s() == 100.0  # not started
    clock.start()
    now[0] = 500_000_000
    assert clock.now_s() == pytest.approx(101.0)
    clock.start()  # a second start keeps the first
    assert clock.now_ns() == 101_000_000_000


def test_replay_drivers_play_at_the_recording_pace(tmp_path: Path) -> None:
    seq_dir = make_sequence(tmp_path / "seq", n_frames=15)
    rp = open_replay(seq_dir)
    t0 = time.monotonic()
    rp.start()
    seen = []
    try:
        seq = 0
        while True:
            got = rp.camera.take(seq, WAIT_S)
            if got is None:
                break
            seq, f = got
            seen.append((time.monotonic() - t0, f.t_s))
            # The AHRS replay catches up with the capture time (at once, unless
            # this machine is busy), then the attitude at the frame is there.
            assert rp.buffer.wait_covered(f.t_s, WAIT_S)
            assert rp.buffer.rotation_at(f.t_s) is not None
    finally:
        assert rp.stop(10)
    assert rp.camera.exhausted and len(seen) >= 10
    # Frame i appears PREROLL_S + (t_i - t_first) + delivery after the start, never early.
    for wall, t in seen:
        assert wall >= PREROLL_S + (t - 1000.0) + FRAME_DELIVERY_S - 0.005
    assert seen[-1][0] < PREROLL_S + 14 / 30 + 5.0
    assert rp.stop_times_s and max(rp.stop_times_s.values()) < 1.0


# --------------------------------------------------------------------------- recording


def test_recording_from_replay_reproduces_the_fixture(shared_data: Path, tmp_path: Path) -> None:
    src = shared_data / FIXTURE
    out = tmp_path / "rec"
    result = record(load_config(None), out, replay_dir=src)
    assert_complete(result, 16)
    assert_same_frames(src, out, at_least=result.frames)
    # Attitude: ground truth samples recorded at their own stamps.
    assert attitude_error_deg(src, out) < 0.01
    cam = open_sequence(out).camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.depth_scale) == (535.4, 539.2, 320.1, 247.6, 5000.0)
    assert result.stop_times_s and max(result.stop_times_s.values()) < 1.0


def test_recording_keeps_attitude_mount_and_depth_units(tmp_path: Path) -> None:
    src = make_sequence(tmp_path / "seq", n_frames=20)
    out = tmp_path / "rec"
    result = record(load_config(None), out, replay_dir=src)
    assert_complete(result, 20)
    assert_same_frames(src, out, at_least=result.frames)
    assert attitude_error_deg(src, out) < 0.01
    rec = open_sequence(out)
    assert rec.camera.q_B_C_xyzw == pytest.approx((0.5, 0.5, 0.5, 0.5))
    assert rec.camera.depth_scale == 1000.0
    # Every attitude sample from the preroll to the tail, at its own stamp.
    played = open_sequence(src).attitude.t_s
    played = played[(played >= 1000.0 - PREROLL_S - 1e-6) & (played <= 1000.0 + 19 / 30 + 0.2)]
    assert np.allclose(rec.attitude.t_s, played, atol=1e-6)
    with pytest.raises(NislamError, match="already holds a recording"):
        SequenceWriter(out)


def run_record(args: list[str], **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "onboard.cli", "record", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def wait_for_listed_frames(rgb_txt: Path, n: int, proc: subprocess.Popen) -> int:
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        if rgb_txt.exists():
            listed = sum(1 for line in rgb_txt.read_text().splitlines()
                         if line and not line.startswith("#"))
            if listed >= n:
                return listed
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.02)  # polling a file for a condition, with a deadline
    raise AssertionError(f"{rgb_txt} never listed {n} frames")


def test_killed_recorder_leaves_a_readable_sequence(tmp_path: Path) -> None:
    src = make_sequence(tmp_path / "seq", n_frames=90)  # 3 s of frames
    out = tmp_path / "rec"
    proc = run_record(["--out", str(out), "--replay", str(src)])
    try:
        wait_for_listed_frames(out / "rgb.txt", 10, proc)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=WAIT_S)
    assert proc.returncode == -signal.SIGKILL
    rec = open_sequence(out)
    n = assert_same_frames(src, out, at_least=10)
    assert n < 90  # killed mid-way
    assert rec.attitude is not None
    assert attitude_error_deg(src, out) < 0.01
    # Every listed line is whole; nothing listed is missing or partial.
    for name in ("rgb.txt", "depth.txt", "attitude.txt"):
        assert (out / name).read_text().endswith("\n")


def test_sigterm_stops_the_recorder_cleanly(tmp_path: Path) -> None:
    src = make_sequence(tmp_path / "seq", n_frames=90)
    out = tmp_path / "rec"
    proc = run_record(["--out", str(out), "--replay", str(src)])
    try:
        wait_for_listed_frames(out / "rgb.txt", 5, proc)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr
    assert "recorded" in stdout and "driver stop times" in stdout
    assert_same_frames(src, out, at_least=5)


def test_record_cli_rejects_bad_arguments(tmp_path: Path) -> None:
    proc = run_record(["--out", str(tmp_path / "x"), "--seconds", "0"])
    _out, err = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == 1 and "--seconds must be > 0" in err
    proc = run_record(["--out", str(tmp_path / "y"), "--replay", str(tmp_path / "none")])
    _out, err = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == 1 and "does not exist" in err


# --------------------------------------------------------------------------- live path


def test_recording_from_stand_in_hardware(tmp_path: Path) -> None:
    """`record` on the live path: a stand-in OAK-D (fake depthai) and a
    simulated myAHRS+ process behind a pty, both through make_hardware."""
    from drivers.hardware import make_hardware
    from peers.fake_depthai import FakeDai
    from test_myahrs import DeviceProcess

    link = tmp_path / "myahrs"
    dev = DeviceProcess(link)
    try:
        dev.expect("plugged")
        cfg = load_config(None, {"myahrs.port": str(link), "oak.width": 64, "oak.height": 40,
                                 "mavlink.mount": "forward", "ahrs.source": "myahrs"})
        fake = FakeDai()
        hw = make_hardware(cfg, camera=True, dai_loader=lambda: fake)
        assert hw.ahrs is not None and hw.camera is not None and hw.link is None
        out = tmp_path / "rec"
        result = record(cfg, out, seconds=1.5, hardware=hw)
    finally:
        dev.close()
    assert result.frames >= 10 and result.attitude_samples >= 50
    assert set(result.stop_times_s) == {"oak", f"myahrs:{link}"}
    rec = open_sequence(out)
    assert len(rec) == result.frames and rec.camera.depth_scale == 1000.0
    r_b_c = Rotation.from_quat(rec.camera.q_B_C_xyzw).as_matrix()
    assert np.allclose(r_b_c @ [0, 0, 1], [1, 0, 0])  # forward mount written
    att, _ = attitude_for_replay(rec, AttitudeErrorModel())
    covered = [att.rotation_at(float(t)) is not None for t in rec.frame_times_s]
    assert sum(covered) >= len(covered) - 2  # the AHRS covers the frames (first may precede it)
    # The simulated AHRS yaws 0.01 rad per sample, about body z.
    yaw = Rotation.from_quat(rec.attitude.q_xyzw).as_euler("zyx")[:, 0]
    steps = np.diff(np.unwrap(yaw))
    assert np.median(steps) == pytest.approx(0.01, abs=1e-4)
    assert math.isfinite(result.seconds)
