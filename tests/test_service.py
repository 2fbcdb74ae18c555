"""The onboard service end to end (hardware-in-the-loop replay): `nislam run
--replay` on synthetic flights as a subprocess, a pymavlink peer in another
process (tests/mavlink_peer.py) and a zenoh subscriber in this one, all on
127.0.0.1; and the systemd notify/watchdog protocol under a fake NOTIFY_SOCKET."""

from __future__ import annotations

import csv
import json
import math
import socket
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from subproc import REPO, JsonLinesProcess, free_port, python_script

from onboard.app.config import load_config
from onboard.app.sdnotify import Notifier
from onboard.app.service import Service
from onboard.app.sources import replay_sources
from onboard.core.camera import CameraIntrinsics
from onboard.core.evaluation import umeyama_se3
from onboard.fusion.registry import make_tracker
from onboard.outputs.settings import ZenohConfig
from onboard.outputs.zenoh_out import session_config
from sim_replay.faults import inject_faults
from sim_replay.sim import SimOptions, simulate
from sim_replay.tum import open_sequence

NISLAM = REPO / ".venv" / "bin" / "nislam"
PEER = REPO / "tests" / "mavlink_peer.py"
GAP_AT_S, GAP_S = 2.0, 1.0  # the attitude gap of the damaged flight
LOST, DEGRADED, ACTIVE, STANDBY = 8, 5, 4, 3  # HEARTBEAT system_status


@pytest.fixture(scope="module")
def flights(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A clean 8 s orbit and a damaged copy: a 1 s attitude gap at 2 s, two
    dropped frames and a corrupt depth image."""
    root = tmp_path_factory.mktemp("flights")
    clean = root / "circle"
    simulate("circle", clean, SimOptions(seconds=8.0, width=320, height=240), progress=False)
    damaged = root / "circle_faults"
    inject_faults(clean, damaged, f"att-gap:{GAP_S}@{GAP_AT_S},drop:2,corrupt:1", seed=1)
    return {"clean": clean, "damaged": damaged}


class StatusSubscriber:
    """A zenoh session listening on 127.0.0.1 that the service connects to;
    collects `nislam/<vehicle>/status` messages."""

    def __init__(self, vehicle: str) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
        self.session = zenoh.open(session_config(ZenohConfig(listen=(self.endpoint,))))
        self.statuses: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        self._sub = self.session.declare_subscriber(f"nislam/{vehicle}/status", self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.statuses.append(json.loads(sample.payload.to_bytes()))

    def states(self) -> list[str]:
        with self._lock:
            return [s["state"] for s in self.statuses]

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()


# The CI machine is shared and its host pauses it for up to a second at a
# time. The test profile plays the flight at a third of real time and gives the health
# timeouts room for such a pause, so a stall shows as a late frame rather than
# a lost spell; what the tests assert (the poses sent, the states, the reset
# counter) is what the service must get right at any pace. tests/test_health.py
# checks the thresholds themselves on a fake clock.
TEST_PROFILE = """[mavlink]
stale_s = 3.0
[nislam]
max_coast_s = 3.0
[service]
stats_period_s = 0.5
replay_speed = 0.35
frame_timeout_s = 3.0
degraded_gap_s = 2.0
"""


def start_service(seq: Path, out: Path, mav_port: int, zenoh_ep: str, *extra: str,
                  mavlink_keys: str = "", tracker: str | None = "nislam") -> JsonLinesProcess:
    """`extra` lines go into [service], `mavlink_keys` into [mavlink].
    `tracker`: NI-SLAM unless told (what a pose gap means is its rule: no
    attitude, no pose); None runs `nislam run`'s own default, the fused one."""
    cfg = out.parent / f"{out.name}.toml"
    cfg.write_text(TEST_PROFILE.replace("[mavlink]\n", "[mavlink]\n" + mavlink_keys)
                   + "".join(extra))
    return JsonLinesProcess([
        str(NISLAM), "run", "--replay", str(seq), "--config", str(cfg), "--out", str(out),
        "--mavlink", f"udpout:127.0.0.1:{mav_port}", "--zenoh-connect", zenoh_ep,
        "--vehicle", "hil", *(["--tracker", tracker] if tracker else []),
    ])


def run_with_peers(seq: Path, out: Path, *extra: str, sigterm_after_poses: int | None = None,
                   tracker: str | None = "nislam"
                   ) -> tuple[int, list[dict], list[str], JsonLinesProcess]:
    """Run the service on `seq` until it ends (or SIGTERM after that many
    poses); returns (exit code, MAVLink messages, zenoh status states, process)."""
    port = free_port()
    peer = JsonLinesProcess(python_script(PEER, f"udpin:127.0.0.1:{port}"))
    peer.wait_for(lambda lines: any(m.get("ready") for m in lines), 60, "peer ready")
    sub = StatusSubscriber("hil")
    svc = start_service(seq, out, port, sub.endpoint, *extra, tracker=tracker)
    try:
        if sigterm_after_poses is not None:
            peer.wait_for(lambda ls: sum(m.get("mavpackettype") == "ODOMETRY" for m in ls)
                          >= sigterm_after_poses, 120, "poses")
            assert svc.proc.poll() is None, "the flight ended before SIGTERM"
            rc = svc.stop()
        else:
            rc = svc.proc.wait(120)
    finally:
        svc.stop()
        peer.stop()
        states = sub.states()
        svc.statuses = list(sub.statuses)  # type: ignore[attr-defined]
        sub.close()
    msgs = [m for m in peer.lines if "mavpackettype" in m and m.get("src_component") == 197]
    return rc, msgs, states, svc


def of(msgs: list[dict], kind: str) -> list[dict]:
    return [m for m in msgs if m["mavpackettype"] == kind]


def recording_times(odometry: list[dict], out: Path) -> np.ndarray:
    """The recording's stamps of ODOMETRY messages: time_usec is the host's
    monotonic time the replay reached them (metrics.json host_clock)."""
    clock = json.loads((out / "metrics.json").read_text())["host_clock"]
    t_host = np.array([m["time_usec"] * 1e-6 for m in odometry])
    t = clock["recording_t0_s"] + (t_host - clock["host_t0_s"]) * clock["speed"]
    return np.round(t, 6)  # the recording's stamps are whole microseconds; time_usec too


def ate_of_odometry(odometry: list[dict], seq_dir: Path, out: Path) -> float:
    """ATE RMSE of the ODOMETRY positions against ground truth, each stretch
    of one reset_counter value SE(3)-aligned on its own: a bumped counter
    tells the flight controller that the poses after it start anew."""
    gt = open_sequence(seq_dir).groundtruth
    assert gt is not None
    t = recording_times(odometry, out)
    p_est = np.array([[m["x"], m["y"], m["z"]] for m in odometry])
    counter = np.array([m["reset_counter"] for m in odometry])
    p_gt, _, valid = gt.interpolate(t, 0.2)
    assert valid.all()
    sq = []
    for c in np.unique(counter):
        sel = counter == c
        if sel.sum() < 3:  # too short to align: nothing to score
            continue
        R, tr = umeyama_se3(p_est[sel], p_gt[sel])
        sq.append(np.sum((p_est[sel] @ R.T + tr - p_gt[sel]) ** 2, axis=1))
    return float(np.sqrt(np.mean(np.concatenate(sq))))


def gap_window(seq_dir: Path) -> tuple[float, float]:
    manifest = json.loads((seq_dir / "faults.json").read_text())
    gap = next(f for f in manifest["faults"] if f["kind"] == "att-gap")
    return gap["stamps"][0], gap["until"][0]


# --------------------------------------------------------------------------- HIL replay


def test_service_feeds_the_autopilot_and_stops_cleanly_on_sigterm(
        flights: dict[str, Path], tmp_path: Path) -> None:
    rc, msgs, states, svc = run_with_peers(flights["clean"], tmp_path / "out",
                                           sigterm_after_poses=30)
    assert rc == 0, svc.stderr[-2000:]
    odometry = of(msgs, "ODOMETRY")
    assert len(odometry) >= 30
    ate = ate_of_odometry(odometry, flights["clean"], tmp_path / "out")
    print(f"ATE of the poses received over MAVLink: {ate * 1e3:.1f} mm ({len(odometry)} poses)")
    assert ate < 0.02
    assert len({m["reset_counter"] for m in odometry}) == 1
    t_usec = [m["time_usec"] for m in odometry]
    assert t_usec == sorted(t_usec)
    # Capture time on the host's clock: the peer (same CLOCK_MONOTONIC) got
    # each pose after its capture, well within a second at a third of real time.
    latency_s = np.array([m["t"] - m["time_usec"] * 1e-6 for m in odometry])
    assert (latency_s > 0).all() and np.median(latency_s) < 0.5, latency_s
    # starting, then tracking: over MAVLink (heartbeat and status texts) and zenoh.
    status = [m["system_status"] for m in of(msgs, "HEARTBEAT")]
    assert STANDBY in status and ACTIVE in status
    assert status.index(STANDBY) < status.index(ACTIVE) and LOST not in status
    texts = [m["text"] for m in of(msgs, "STATUSTEXT")]
    starting = next(i for i, t in enumerate(texts) if "starting" in t)
    assert any("tracking" in t for t in texts[starting + 1:]), texts
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert len(texts) == metrics["health_changes"], texts  # one STATUSTEXT per transition
    assert "tracking" in states and "lost" not in states
    assert set(states) <= {"starting", "tracking", "degraded"}  # degraded: this machine paused
    if "starting" in states:  # published before the subscriber was matched, or not
        assert states.index("starting") < states.index("tracking")
    # SIGTERM: the frame finished, outputs flushed, results written, summary printed.
    assert metrics["frames_tracked"] >= len(odometry)
    assert any(line.startswith("ATE RMSE") for line in svc.text), svc.text
    assert any("Hz" in line and "key frames" in line for line in svc.text)  # statistics lines
    # Latency (onboard/app/latency.py): each pose written to the link after the
    # tracker was done with it and before the peer received it (one host clock).
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    assert run["untrusted_sent"] == 0 and run["frames_processed"] == metrics["frames"]
    assert run["latency_ms"]["kind"] == "capture_to_written" and run["first_pose_s"] > 0
    # [service] realtime_priority is 0 by default (onboard/app/priority.py)
    assert run["scheduling"] == "normal"
    assert 0.0 <= run["host_steal_share"] < 1.0  # /proc/stat's steal over the run (cpu_steal.py)
    rows = {round(float(r["capture_s"]) * 1e6): r
            for r in csv.DictReader((tmp_path / "out" / "latency.csv").open())}
    received_ms = {m["time_usec"]: m["t"] * 1e3 - m["time_usec"] / 1e3 for m in odometry}
    both = [(float(rows[k]["done_ms"]), float(rows[k]["written_ms"]), received_ms[k])
            for k in received_ms if k in rows and rows[k]["written_ms"]]
    assert len(both) >= 0.9 * len(odometry)
    # (written: when the send returned; the peer on the other core may read it
    # before this process, preempted, takes the time: a few ms at most)
    assert all(done <= written <= received + 5.0 for done, written, received in both), both
    assert np.median([r - w for _d, w, r in both]) >= -0.5, both
    assert any("latency" in line and "p99" in line for line in svc.text)  # the summary
    status = [s for s in svc.statuses if s.get("latency_ms", {}).get("p50") is not None]
    assert status and status[-1]["latency_ms"]["kind"] == "capture_to_written"


def test_a_restart_mid_flight_tells_the_autopilot_with_reset_counter_and_time_goes_on(
        flights: dict[str, Path], tmp_path: Path) -> None:
    """Stop the service mid-flight and start it again on the same vehicle (the
    same state directory): the new process's world starts at its first pose,
    so the feed steps back; that first pose carries a new reset_counter (the
    previous one + 1) and time_usec keeps increasing."""
    port = free_port()
    peer = JsonLinesProcess(python_script(PEER, f"udpin:127.0.0.1:{port}"))
    peer.wait_for(lambda lines: any(m.get("ready") for m in lines), 60, "peer ready")
    sub = StatusSubscriber("hil")
    state = f'state_dir = "{tmp_path / "state"}"\n'

    def poses() -> list[dict]:
        return [m for m in peer.lines if m.get("mavpackettype") == "ODOMETRY"]

    try:
        for run, n in (("first", 75), ("second", 10)):
            before = len(poses())
            svc = start_service(flights["clean"], tmp_path / run, port, sub.endpoint,
                                mavlink_keys=state)
            try:
                peer.wait_for(lambda ls: len(poses()) >= before + n, 120, f"{run} run's poses")
            finally:
                assert svc.stop() == 0, svc.stderr[-2000:]
            if run == "first":
                first_run = poses()
    finally:
        peer.stop()
        sub.close()
    odometry = poses()
    k = len(first_run)
    last, new = odometry[k - 1], odometry[k]
    step_m = math.dist([last["x"], last["y"], last["z"]], [new["x"], new["y"], new["z"]])
    assert step_m > 0.3  # 2.5 s into the orbit, then a new world from the start pose
    assert len({m["reset_counter"] for m in first_run}) == 1
    assert new["reset_counter"] == (last["reset_counter"] + 1) % 256
    t_usec = [m["time_usec"] for m in odometry]
    assert all(b > a for a, b in zip(t_usec, t_usec[1:]))  # across the restart too
    gap_s = (new["time_usec"] - last["time_usec"]) / 1e6
    print(f"restart: step {step_m:.2f} m, reset_counter {last['reset_counter']} -> "
          f"{new['reset_counter']}, time_usec +{gap_s:.1f} s")


def test_service_survives_a_damaged_flight_and_never_sends_an_untrusted_pose(
        flights: dict[str, Path], tmp_path: Path) -> None:
    seq = flights["damaged"]
    rc, msgs, states, svc = run_with_peers(seq, tmp_path / "out")
    assert rc == 0, svc.stderr[-2000:]
    odometry = of(msgs, "ODOMETRY")
    t0, t1 = gap_window(seq)
    times = recording_times(odometry, tmp_path / "out")
    # No attitude, no NI-SLAM pose: nothing is sent for the frames inside the gap.
    assert not np.any((times > t0 + 0.05) & (times < t1 - 0.05))
    before = [m["reset_counter"] for m, t in zip(odometry, times) if t < t0]
    after = [m["reset_counter"] for m, t in zip(odometry, times) if t > t1]
    assert before and after and len(set(before)) == 1
    assert min((c - before[0]) % 256 for c in after) >= 1  # bumped (uint8, may wrap)
    assert LOST in [m["system_status"] for m in of(msgs, "HEARTBEAT")]
    # Resumed: tracking again after the last lost spell (the state may end
    # degraded if this machine paused near the end: recover_s has not run out).
    assert "lost" in states, states
    last_lost = len(states) - 1 - states[::-1].index("lost")
    assert "tracking" in states[last_lost + 1:], states
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["lost_reasons"].get("no attitude", 0) >= 5  # frames in the gap, said why
    expected = json.loads((seq / "faults.json").read_text())["expected"]
    for key, n in expected.items():  # what the reader skipped is counted and reported
        # (a corrupt frame this machine fell too far behind to read is
        # counted as late at the source instead)
        late = metrics["frames_late_at_source"] if key == "unreadable_files" else 0
        assert metrics["skipped"][key] + late >= n, (key, metrics["skipped"], late)


def test_the_default_fused_tracker_keeps_the_feed_through_an_attitude_gap_without_a_reset(
        flights: dict[str, Path], tmp_path: Path) -> None:
    """`nislam run`'s own tracker (fused, issue 19) on the damaged flight:
    through the AHRS gap FastORB carries the pose, so the feed goes on with
    no reset and no frame is lost for want of attitude; the fallback, which
    only NI-SLAM alone needs, is not used even when configured."""
    seq = flights["damaged"]
    rc, msgs, states, svc = run_with_peers(seq, tmp_path / "out",
                                           'fallback_tracker = "fastorb"\n', tracker=None)
    assert rc == 0, svc.stderr[-2000:]
    odometry = of(msgs, "ODOMETRY")
    t0, t1 = gap_window(seq)
    times = recording_times(odometry, tmp_path / "out")
    inside = (times > t0 + 0.05) & (times < t1 - 0.05)
    assert inside.sum() >= 5  # posed inside the gap (NI-SLAM alone sends nothing there)
    assert len({m["reset_counter"] for m in odometry}) == 1  # one epoch: no reset, no switch
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["tracker"] == "fused" and metrics["fallback_tracker"] == ""
    assert metrics["tracker_switches"] == 0
    assert metrics["lost_reasons"].get("no attitude", 0) == 0, metrics["lost_reasons"]
    # Used for the gap's frames, NI-SLAM left out of them and said why.
    left_out = metrics["fusion"]["trackers"]["nislam"]["left_out"]
    assert left_out.get("lost: no attitude", 0) >= 5, left_out
    ate = ate_of_odometry(odometry, seq, tmp_path / "out")
    assert ate < 0.02, ate
    print(f"ATE through the gap, fused: {ate * 1e3:.1f} mm")


def test_fallback_tracker_keeps_the_feed_through_an_attitude_gap(
        flights: dict[str, Path], tmp_path: Path) -> None:
    seq = flights["damaged"]
    rc, msgs, states, svc = run_with_peers(seq, tmp_path / "out",
                                           'fallback_tracker = "fastorb"\n')
    assert rc == 0, svc.stderr[-2000:]
    odometry = of(msgs, "ODOMETRY")
    t0, t1 = gap_window(seq)
    times = recording_times(odometry, tmp_path / "out")
    inside = (times > t0 + 0.05) & (times < t1 - 0.05)
    assert inside.sum() >= 5  # FastORB posed the frames NI-SLAM could not
    counters = [(m["reset_counter"] - odometry[0]["reset_counter"]) % 256 for m in odometry]
    # Out and back: a bump at each switch (and one per restart of either
    # tracker, should this machine starve it of frames).
    assert counters == sorted(counters) and counters[-1] >= 2
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["tracker_switches"] == 2
    assert DEGRADED in [m["system_status"] for m in of(msgs, "HEARTBEAT")]
    assert "degraded" in states
    # No frame went without a pose for want of attitude: FastORB took them.
    assert metrics["lost_reasons"].get("no attitude", 0) == 0, metrics["lost_reasons"]
    ate = ate_of_odometry(odometry, seq, tmp_path / "out")
    print(f"ATE through the gap with the fallback: {ate * 1e3:.1f} mm")
    assert ate < 0.05


# --------------------------------------------------------------------------- systemd notify


class StallingTracker:
    """A real tracker whose `track()` blocks on `release` from frame `at` on."""

    def __init__(self, inner: Any, at: int, release: threading.Event) -> None:
        self.inner, self.at, self.name = inner, at, inner.name
        self.frames = 0
        self.stalled = threading.Event()
        self.release = release
        self.t_s: list[float] = []

    def track(self, frame: Any, attitude: Any) -> Any:
        self.frames += 1
        self.t_s.append(frame.t_s)
        if self.frames == self.at:
            self.stalled.set()
            self.release.wait(30)
        return self.inner.track(frame, attitude)

    def finish(self) -> Any:
        return self.inner.finish()


def recv_all(sock: socket.socket, timeout_s: float) -> list[str]:
    """Datagrams arriving within `timeout_s` (a window of observation)."""
    sock.settimeout(timeout_s)
    out = []
    try:
        while True:
            out.append(sock.recv(4096).decode())
    except TimeoutError:
        return out


def wait_message(sock: socket.socket, prefix: str, timeout_s: float = 30.0) -> list[str]:
    sock.settimeout(timeout_s)
    seen = []
    while True:
        seen.append(sock.recv(4096).decode())
        if seen[-1].startswith(prefix):
            return seen


def test_ready_and_watchdog_pings_come_from_the_loop_and_stop_when_it_stalls(
        flights: dict[str, Path], tmp_path: Path) -> None:
    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    period_s = 0.4  # pings every 0.2 s
    notifier = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": str(int(period_s * 1e6))})
    cfg = load_config()
    sources, cfg = replay_sources(cfg, flights["clean"])
    holder: dict[str, StallingTracker] = {}
    release = threading.Event()

    def factory(name: str, intr: CameraIntrinsics, c: Any) -> StallingTracker:
        holder["t"] = StallingTracker(make_tracker(name, intr, c), at=10, release=release)
        return holder["t"]

    stop = threading.Event()
    service = Service(cfg, sources, stop, notifier=notifier, tracker_factory=factory)
    thread = threading.Thread(target=service.run, daemon=True)
    thread.start()
    try:
        before_ready = wait_message(sock, "READY=1")
        assert any(m == "WATCHDOG=1" for m in before_ready)  # the loop pings while it waits
        pings = [m for m in wait_message(sock, "WATCHDOG=1") if m == "WATCHDOG=1"]
        assert pings
        tracker = holder["t"]
        assert tracker.stalled.wait(120)
        recv_all(sock, 0.05)  # a ping sent just before the stall
        silent = recv_all(sock, 3 * period_s)
        assert "WATCHDOG=1" not in silent  # a hung loop stops pinging: systemd restarts it
        frames_at_stall = tracker.frames
        release.set()
        wait_message(sock, "WATCHDOG=1", 10)  # the loop turns again: pings resume
        # The frames that came during the stall were dropped, not queued: the
        # next one tracked is the newest.
        assert service.stats.frames >= frames_at_stall - 1
        tracker_t = tracker.t_s
        while len(tracker_t) <= frames_at_stall:
            wait_message(sock, "WATCHDOG=1", 10)
        assert tracker_t[frames_at_stall] - tracker_t[frames_at_stall - 1] > 1.0
        # ~1.2 s of frames came meanwhile: dropped by the slot, or skipped
        # by the replay camera when this machine itself fell behind.
        assert sources.camera.slot.stats.dropped + sources.camera.late >= 20
    finally:
        release.set()
        stop.set()
        thread.join(30)
    assert not thread.is_alive()
    rest = recv_all(sock, 0.5)
    assert "STOPPING=1" in rest
    sock.close()


# --------------------------------------------------------------------------- live path


def test_service_on_stand_in_hardware(tmp_path: Path) -> None:
    """The hardware path of `nislam run`: a stand-in OAK-D (fake depthai, the
    real driver code) and a simulated myAHRS+ process behind a pty, through
    make_hardware; the loop builds the tracker from the device's intrinsics,
    tracks what arrives and stops both drivers."""
    from peers.fake_depthai import FakeDai
    from test_myahrs import DeviceProcess

    from onboard.app.sources import hardware_sources

    link = tmp_path / "myahrs"
    dev = DeviceProcess(link)
    try:
        dev.expect("plugged")
        cfg = load_config(None, {"myahrs.port": str(link), "oak.width": 64, "oak.height": 40,
                                 "ahrs.source": "myahrs", "service.stats_period_s": 0.5})
        sources = hardware_sources(cfg, dai_loader=FakeDai)
        lines: list[str] = []
        stop = threading.Event()
        service = Service(cfg, sources, stop, emit=lines.append)
        done: list = []
        thread = threading.Thread(target=lambda: done.append(service.run()), daemon=True)
        thread.start()
        # Until 10 frames and a statistics line are in (however slowly this
        # machine runs), then a stop as SIGTERM would give.
        deadline = time.monotonic() + 120
        while (service.stats.frames < 10 or not lines) and time.monotonic() < deadline:
            stop.wait(0.05)  # polling the loop's counters, with a deadline
        stop.set()
        thread.join(60)
        result = done[0]
    finally:
        dev.close()
    m = result.metrics
    assert m["source"] == "OAK-D" and m["attitude_source"] == "myahrs"
    assert m["frames"] >= 10 and service.ready
    assert set(m["stop_times_s"]) == {"oak", f"myahrs:{link}"}
    assert lines and all("Hz" in line for line in lines)
    assert "ate_rmse_m" not in m  # no ground truth on hardware


def test_run_refuses_a_bad_config_with_one_line(tmp_path: Path) -> None:
    import subprocess

    cfg = tmp_path / "bad.toml"
    cfg.write_text('[service]\nfallback_tracker = "nislam"\n')
    proc = subprocess.run([str(NISLAM), "run", "--config", str(cfg), "--sim", "hover"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert proc.stderr.count("\n") == 1 and "service.fallback_tracker" in proc.stderr
    proc = subprocess.run([str(NISLAM), "run", "--loop", "--sim", "hover"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1 and "--loop needs --seconds" in proc.stderr


def test_run_sim_is_the_main_job(tmp_path: Path) -> None:
    """`nislam run --sim`: a flight rendered on the fly, replayed through the
    service, scored at the end (the README's main job, shortened)."""
    import subprocess

    out = tmp_path / "run"
    cfg = tmp_path / "test.toml"
    cfg.write_text(TEST_PROFILE.replace("replay_speed = 0.5", "replay_speed = 0.25"))
    proc = subprocess.run([str(NISLAM), "run", "--sim", "hover", "--seconds", "2", "--out",
                           str(out), "--config", str(cfg)], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "ATE RMSE" in proc.stdout and (out / "flight" / "rgb.txt").exists()
    metrics = json.loads((out / "metrics.json").read_text())
    # Every one of the 60 frames is processed or counted as dropped; at a
    # quarter of real time most get through.
    assert (metrics["frames"] + metrics["frames_dropped"] + metrics["frames_late_at_source"]
            == 60), metrics
    assert metrics["frames_tracked"] >= 20 and metrics["ate_rmse_m"] < 0.01
    assert (out / "trajectory.tum").exists() and (out / "config.toml").exists()
