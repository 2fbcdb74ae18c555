"""Replay drivers and `nislam record`: a recording made through the driver
interfaces reproduces the original sequence; a killed recorder leaves a
readable one; the live path runs on stand-in hardware."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from onboard import NislamError
from onboard.app.config import load_config
from onboard.app.record import SequenceWriter, record
from onboard.core.attitude import AttitudeBuffer
from onboard.core.camera import CameraModel
from onboard.core.messages import RgbdFrame
from onboard.core.sources import FrameSlot
from sim_replay.attitude import AttitudeErrorModel, attitude_for_replay
from sim_replay.sources import (
    FRAME_DELIVERY_S,
    PREROLL_S,
    ReplayAttitude,
    ReplayClock,
    open_replay,
)
from sim_replay.tum import open_sequence

os.environ["DEPTHAI_PROTOCOL"] = "usb"

WAIT_S = 60.0
FIXTURE = "fixtures/tum_fr3_office_16frames"
# Replay speed of the recordings meant to hold every frame: ten times the time
# per frame (0.33 s at 30 Hz), so a machine that stalls for a few hundred ms
# rarely decodes behind the replay clock. What it skips anyway is counted
# (assert_accounted); the count is not asserted, it depends on the machine.
SLOW_PACE = 0.1


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
    """Every recorded frame equals the original at its stamp, bit for bit;
    returns how many were compared. The replay plays the original at its
    fitted capture times (sim_replay/stamps.py) and the recording keeps
    those: read it back as recorded."""
    a, b = open_sequence(original), open_sequence(recorded, stamp_window_s=0.0)
    by_t = {round(f.t_s, 6): f for f in a.frames()}
    n = 0
    for f in b.frames():
        o = by_t[round(f.t_s, 6)]
        assert np.array_equal(o.bgr, f.bgr)
        assert np.array_equal(o.depth_m, f.depth_m)
        n += 1
    assert n >= at_least and b.skipped.unreadable_files == 0 and b.skipped.missing_files == 0
    return n


def assert_accounted(result, n_frames: int) -> None:
    """Every source frame was recorded, dropped (replaced in the newest-frame
    slot or the writer's queue) or skipped as late at the source (decoded
    behind the replay clock), each counted: nothing is lost silently. How many
    land in each count depends on the machine's load, so that is not
    asserted; the last frame is never late or replaced, so one is recorded."""
    assert result.frames + result.frames_dropped + result.frames_late_at_source == n_frames, result
    assert result.frames >= 1, result


def attitude_error_deg(original: Path, recorded: Path) -> float:
    """Largest angle between the two sequences' R_W_C at the recorded frames."""
    a, b = open_sequence(original), open_sequence(recorded)
    # the samples as recorded, not the local fit over them (core/attitude_smoothing.py)
    att_a, _ = attitude_for_replay(a, AttitudeErrorModel(), smoothing_s=0.0)
    att_b, _ = attitude_for_replay(b, AttitudeErrorModel(), smoothing_s=0.0)
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


class SteppedClock:
    """A monotonic clock (ns) that only the test moves."""

    def __init__(self) -> None:
        self.t_ns = 0

    def __call__(self) -> int:
        return self.t_ns


def test_replay_camera_skips_frames_already_stale_and_counts_them(tmp_path: Path) -> None:
    """Decoding behind the replay clock: a frame whose successor is already
    due is skipped and counted as late (a camera's slot would drop it), the
    others are published at their stamps, never before."""
    seq_dir = make_sequence(tmp_path / "seq", n_frames=6)
    clock = SteppedClock()
    rp = open_replay(seq_dir, mono_ns=clock)
    stamps = [float(t) for t in rp.seq.frame_times_s]
    start_s = stamps[0] - PREROLL_S  # recording time at clock 0

    def set_recording_time(t_s: float) -> None:
        clock.t_ns = int(round((t_s - start_s) * 1e9))

    rp.clock.start()
    # Past frame 3's delivery, before frame 4's: frames 0-2 have a due
    # successor (late), frame 3 is due now, frame 4 not yet.
    set_recording_time(stamps[3] + FRAME_DELIVERY_S + 0.005)
    cam = rp.camera
    cam.start()
    try:
        got = cam.take(0, WAIT_S)
        assert got is not None and got[1].t_s == stamps[3]
        assert cam.late == 3 and cam.slot.stats.put == 1
        # Frame 4 waits for its time while the clock stands still.
        assert cam.take(got[0], 0.2) is None and cam.slot.stats.put == 1
        set_recording_time(stamps[-1] + 1.0)  # both remaining frames due
        seen = [got[1].t_s]
        seq = got[0]
        while (got := cam.take(seq, WAIT_S)) is not None:
            seq = got[0]
            seen.append(got[1].t_s)
    finally:
        assert rp.stop(10)
    assert cam.exhausted and (cam.late, cam.published, cam.unreadable) == (3, 3, 0)
    # Frame 4 was already waiting for its time (decoded), so it is published,
    # not skipped; the slot may replace it by frame 5 before it is taken.
    assert seen[-1] == stamps[5] and set(seen) <= set(stamps[3:])
    assert len(seen) + cam.slot.stats.dropped == cam.published


def test_replay_camera_decodes_the_next_frame_once_the_loop_took_the_last(tmp_path: Path) -> None:
    """Like the OAK's driver thread, which sleeps on its device queue after a
    hand-over, the replay camera leaves its core to the loop that wakes for
    the frame: it decodes the next frame only once the frame was taken (or
    its `handover_wait_s` ran out)."""
    seq_dir = make_sequence(tmp_path / "seq", n_frames=4)
    rp = open_replay(seq_dir)
    cam = rp.camera
    cam.handover_wait_s = WAIT_S
    read = rp.seq.read_frame
    taken_at_read: list[tuple[int, int]] = []
    second_read = threading.Event()

    def read_frame(i: int):
        taken_at_read.append((cam.slot.stats.put, cam.slot.stats.taken))
        if i == 1:
            second_read.set()
        return read(i)

    rp.seq.read_frame = read_frame
    put = cam.slot.put
    first_put = threading.Event()

    def put_and_tell(frame):
        seq = put(frame)
        first_put.set()
        return seq

    cam.slot.put = put_and_tell
    rp.start()
    try:
        assert first_put.wait(WAIT_S)
        # Frame 0 is in the slot, not taken: the next is not decoded meanwhile.
        assert not second_read.wait(0.5)
        seq = 0
        while (got := cam.take(seq, WAIT_S)) is not None:
            seq = got[0]
    finally:
        assert rp.stop(10)
    # Held 0.5 s on frame 0, the camera skipped what went stale meanwhile.
    assert cam.published + cam.late == 4 and len(taken_at_read) == cam.published >= 2
    assert all(put == taken for put, taken in taken_at_read)  # each read after the take


def test_replay_camera_decodes_a_frame_just_before_it_is_due(tmp_path: Path) -> None:
    """The decoding of a frame starts its `DecodeLead` before the frame's
    delivery, not at the last hand-over, where it ran beside the loop's
    tracker (on the 2-core VM it doubled the tracker's wall time)."""
    seq_dir = make_sequence(tmp_path / "seq", n_frames=20)
    rp = open_replay(seq_dir)
    cam = rp.camera
    due = rp.seq.frame_times_s + cam.delivery_s
    read = rp.seq.read_frame
    starts: list[tuple[int, float, float]] = []  # (frame, recording time, lead [s])

    def read_frame(i: int):
        starts.append((i, rp.clock.now_s(), cam.decode_lead.lead_s))
        time.sleep(0.003)  # a decode of at least 3 ms: the lead is at least 7.5 ms
        return read(i)

    rp.seq.read_frame = read_frame
    rp.start()
    try:
        seq = 0
        while (got := cam.take(seq, WAIT_S)) is not None:
            seq = got[0]
    finally:
        assert rp.stop(10)
    assert cam.published + cam.late == 20 and len(starts) == cam.published
    assert math.isinf(starts[0][2])  # nothing timed yet: the first frame at once
    timed = starts[1:]
    assert all(t >= due[i] - lead - 1e-3 for i, t, lead in timed)  # not before its lead
    assert all(lead >= 0.0075 for _, _, lead in timed)
    # ... and not at the last hand-over: a frame's decoding starts late in the
    # period after the frame before it was delivered (before: at once).
    after_last = [t - due[i - 1] for i, t, _ in timed if i > 0]
    assert np.median(after_last) > 0.3 * (due[1] - due[0])


def test_replay_drivers_play_at_the_recording_pace(tmp_path: Path) -> None:
    seq_dir = make_sequence(tmp_path / "seq", n_frames=15)
    rp = open_replay(seq_dir)
    t0 = time.monotonic()
    rp.start()
    seen = []
    try:
        seq = 0
        while (got := rp.camera.take(seq, WAIT_S)) is not None:
            seq, f = got
            seen.append((time.monotonic() - t0, f.t_s))
            # The AHRS replay catches up with the capture time (at once, unless
            # this machine is busy), then the attitude at the frame is there.
            assert rp.buffer.wait_covered(f.t_s, WAIT_S)
            assert rp.buffer.rotation_at(f.t_s) is not None
    finally:
        assert rp.stop(10)
    cam = rp.camera
    print(f"replay pace: {len(seen)} of 15 frames taken, {cam.late} late at the source, "
          f"{cam.slot.stats.dropped} replaced in the slot; last taken after "
          f"{seen[-1][0]:.2f} s (due after {PREROLL_S + 14 / 30 + FRAME_DELIVERY_S:.2f} s); "
          f"stop times {rp.stop_times_s}")
    # Every frame accounted for: taken, replaced in the slot before it was
    # taken, or skipped at the source as late (how many depends on the load).
    assert cam.exhausted and cam.unreadable == 0
    assert cam.published + cam.late == 15
    assert len(seen) + cam.slot.stats.dropped == cam.published
    # In order, each once, and the last one always (nothing replaces it).
    taken = [t for _wall, t in seen]
    assert taken == sorted(set(taken)) and taken[-1] == float(rp.seq.frame_times_s[-1])
    # Frame i appears PREROLL_S + (t_i - t_first) + delivery after the start, never early.
    for wall, t in seen:
        assert wall >= PREROLL_S + (t - 1000.0) + FRAME_DELIVERY_S - 0.005
    assert set(rp.stop_times_s) == {cam.name, "replay_attitude"}


# --------------------------------------------------------------------------- recording


def test_recording_from_replay_reproduces_the_fixture(shared_data: Path, tmp_path: Path) -> None:
    src = shared_data / FIXTURE
    out = tmp_path / "rec"
    result = record(load_config(None), out, replay_dir=src, replay_speed=SLOW_PACE)
    print("\n".join(result.summary_lines()))
    assert_accounted(result, 16)
    assert assert_same_frames(src, out, at_least=result.frames) == result.frames
    # Attitude: ground truth samples recorded at their own stamps.
    assert attitude_error_deg(src, out) < 0.01
    cam = open_sequence(out).camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.depth_scale) == (535.4, 539.2, 320.1, 247.6, 5000.0)
    assert set(result.stop_times_s) == {f"replay_camera:{src.name}", "replay_attitude"}


def test_recording_keeps_attitude_mount_and_depth_units(tmp_path: Path) -> None:
    src = make_sequence(tmp_path / "seq", n_frames=20)
    out = tmp_path / "rec"
    result = record(load_config(None), out, replay_dir=src, replay_speed=SLOW_PACE)
    print("\n".join(result.summary_lines()))
    assert_accounted(result, 20)
    assert assert_same_frames(src, out, at_least=result.frames) == result.frames
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


def test_recording_counts_the_frames_skipped_at_the_source(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A replay whose clock is past every frame when it starts (decoding
    hopelessly behind): its camera skips all but the last frame as late, and
    the recording says so instead of losing them silently."""
    import sim_replay.sources as sources

    open_replay_on_time = sources.open_replay

    def open_replay_behind(*args, **kwargs) -> sources.Replay:
        clock = SteppedClock()
        rp = open_replay_on_time(*args, mono_ns=clock, **kwargs)
        rp.clock.start()  # at 0; then an hour passes before a frame is decoded
        clock.t_ns = 3600 * 10**9
        return rp

    monkeypatch.setattr(sources, "open_replay", open_replay_behind)
    src = make_sequence(tmp_path / "seq", n_frames=20)
    out = tmp_path / "rec"
    result = record(load_config(None), out, replay_dir=src)
    summary = "\n".join(result.summary_lines())
    assert (result.frames, result.frames_dropped, result.frames_late_at_source) == (1, 0, 19)
    assert "frames dropped: 0; late at the source: 19" in summary
    assert_accounted(result, 20)
    assert assert_same_frames(src, out, at_least=1) == 1
    assert open_sequence(out).frame_times_s[0] == open_sequence(src).frame_times_s[-1]


class LastFrameRacesTheEnd:
    """A replay camera whose every frame, the last one too, arrives (and after
    the last, the stream ends) just as the recorder's wait for it times out."""

    def __init__(self, frames: list[RgbdFrame]) -> None:
        self.slot = FrameSlot()
        self.frames = list(frames)
        self.model = CameraModel(50.0, 50.0, 4.0, 3.0, 8, 6, 1000.0)
        self.late = 0

    def wait_camera(self, timeout_s: float) -> CameraModel:
        return self.model

    def take(self, after_seq: int = 0, timeout_s: float = 0.0) -> tuple[int, RgbdFrame] | None:
        got = self.slot.take(after_seq, 0.0)
        if got is None and self.frames:  # nothing yet: the next one comes as the wait ends
            self.slot.put(self.frames.pop(0))
            if not self.frames:
                self.slot.close()
        return got

    @property
    def exhausted(self) -> bool:
        return self.slot.closed


class ReplayStandIn:
    """sim_replay.sources.Replay's interface around one camera source; its
    attitude has played out."""

    attitude_label = "none"

    def __init__(self, camera: LastFrameRacesTheEnd) -> None:
        self.camera = camera
        self.buffer = AttitudeBuffer()
        self.attitude = ReplayAttitude(np.zeros(0), np.zeros((0, 4)), ReplayClock(0.0),
                                       self.buffer.push)
        self.attitude.finished.set()
        self.stop_times_s: dict[str, float] = {}

    def start(self) -> None:
        pass

    def stop(self, timeout_s: float = 5.0) -> bool:
        return True


def test_recording_takes_a_frame_that_comes_as_the_replay_ends(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import sim_replay.sources as sources

    frames = [RgbdFrame(1000.0 + i / 30, np.full((6, 8, 3), i, np.uint8),
                        np.full((6, 8), 1.0 + i / 1000, np.float32)) for i in range(5)]
    replay = ReplayStandIn(LastFrameRacesTheEnd(frames))
    monkeypatch.setattr(sources, "open_replay", lambda *args, **kwargs: replay)
    result = record(load_config(None), tmp_path / "rec", replay_dir=tmp_path)
    assert (result.frames, result.frames_dropped, result.frames_late_at_source) == (5, 0, 0)
    rec = open_sequence(tmp_path / "rec")
    assert [f.t_s for f in rec.frames()] == pytest.approx([f.t_s for f in frames], abs=1e-6)


def run_record(args: list[str], **kw) -> subprocess.Popen:
    """`nislam record` as a subprocess (stdout and stderr piped, text)."""
    return subprocess.Popen([sys.executable, "-m", "onboard.app.cli", "record", *args],
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
    src = make_sequence(tmp_path / "seq", n_frames=90)  # 3 s of frames, 30 s at SLOW_PACE
    out = tmp_path / "rec"
    proc = run_record(["--out", str(out), "--replay", str(src),
                       "--replay-speed", str(SLOW_PACE)])
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
    proc = run_record(["--out", str(out), "--replay", str(src),
                       "--replay-speed", str(SLOW_PACE)])
    try:
        wait_for_listed_frames(out / "rgb.txt", 5, proc)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr
    assert "recorded" in stdout and "driver stop times" in stdout
    assert "late at the source: " in stdout
    assert_same_frames(src, out, at_least=5)


def test_record_cli_rejects_bad_arguments(tmp_path: Path) -> None:
    proc = run_record(["--out", str(tmp_path / "x"), "--seconds", "0"])
    _out, err = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == 1 and "--seconds must be in (0, " in err
    proc = run_record(["--out", str(tmp_path / "y"), "--replay", str(tmp_path / "none")])
    _out, err = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == 1 and "does not exist" in err
    proc = run_record(["--out", str(tmp_path / "z"), "--replay", str(tmp_path / "none"),
                       "--replay-speed", "0"])
    _out, err = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == 1 and "--replay-speed must be in" in err


# --------------------------------------------------------------------------- live path


def listed_stamps(path: Path) -> list[float]:
    """Stamps of the whole lines a list file (rgb.txt, attitude.txt) holds so far."""
    if not path.exists():
        return []
    lines = path.read_text().split("\n")[:-1]  # a line still being appended has no newline
    return [float(line.split()[0]) for line in lines if line and not line.startswith("#")]


def frames_inside_attitude(out: Path) -> tuple[int, int]:
    """(frames within the span of the recorded attitude, attitude samples) so far."""
    att = listed_stamps(out / "attitude.txt")
    if not att:
        return 0, 0
    return sum(att[0] <= t <= att[-1] for t in listed_stamps(out / "rgb.txt")), len(att)


def test_recording_from_stand_in_hardware(tmp_path: Path) -> None:
    """`record` on the live path: a stand-in OAK-D (fake depthai) and a
    simulated myAHRS+ process behind a pty, both through make_hardware. It
    records until the files hold 10 frames inside the attitude's span and 50
    attitude samples, however long a busy machine takes, then is stopped."""
    from peers.fake_depthai import FakeDai
    from test_myahrs import DeviceProcess

    from onboard.app.hardware import make_hardware

    link = tmp_path / "myahrs"
    out = tmp_path / "rec"
    stop = threading.Event()
    outcome: dict = {}
    dev = DeviceProcess(link)
    try:
        dev.expect("plugged")
        cfg = load_config(None, {"myahrs.port": str(link), "oak.width": 64, "oak.height": 40,
                                 "mavlink.mount": "forward", "ahrs.source": "myahrs"})
        fake = FakeDai()
        hw = make_hardware(cfg, camera=True, dai_loader=lambda: fake)
        assert hw.ahrs is not None and hw.camera is not None and hw.link is None

        def run() -> None:
            try:
                outcome["result"] = record(cfg, out, hardware=hw, stop=stop)
            except BaseException as e:  # noqa: BLE001 - re-raised in the test thread
                outcome["error"] = e

        recorder = threading.Thread(target=run, daemon=True)
        recorder.start()
        deadline = time.monotonic() + WAIT_S
        while True:
            frames, samples = frames_inside_attitude(out)
            if frames >= 10 and samples >= 50:
                break
            assert recorder.is_alive() and time.monotonic() < deadline, (outcome, frames, samples)
            time.sleep(0.05)  # polling files for a condition, with a deadline
        stop.set()
        recorder.join(WAIT_S)
        assert not recorder.is_alive()
    finally:
        stop.set()
        dev.close()
    if "error" in outcome:
        raise outcome["error"]
    result = outcome["result"]
    print("\n".join(result.summary_lines()))
    assert result.frames >= 10 and result.attitude_samples >= 50
    assert result.frames_late_at_source == 0  # only a replay skips frames at the source
    assert set(result.stop_times_s) == {"oak", f"myahrs:{link}"}
    rec = open_sequence(out)
    assert len(rec) == result.frames and rec.camera.depth_scale == 1000.0
    r_b_c = Rotation.from_quat(rec.camera.q_B_C_xyzw).as_matrix()
    assert np.allclose(r_b_c @ [0, 0, 1], [1, 0, 0])  # forward mount written
    # Frames and attitude share one clock: frames inside the AHRS's span (the
    # first ones may precede it) have an attitude, except across an outage
    # longer than the reader bridges (a busy machine can stall the device).
    max_gap_s = 0.2
    att, _ = attitude_for_replay(rec, AttitudeErrorModel(), max_gap_s)
    t_att = rec.attitude.t_s
    inside = [float(t) for t in rec.frame_times_s if t_att[0] <= t <= t_att[-1]]
    assert len(inside) >= 10
    for t in inside:
        i = int(np.searchsorted(t_att, t))
        outage = t_att[i] != t and t_att[i] - t_att[i - 1] > max_gap_s
        assert outage or att.rotation_at(t) is not None, t
    # The simulated AHRS yaws 0.01 rad per sample, about body z.
    yaw = Rotation.from_quat(rec.attitude.q_xyzw).as_euler("zyx")[:, 0]
    steps = np.diff(np.unwrap(yaw))
    assert np.median(steps) == pytest.approx(0.01, abs=1e-4)
    assert math.isfinite(result.seconds)
