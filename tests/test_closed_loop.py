"""The closed loop without an autopilot: `nislam run --sim-follow` against a
simulated vehicle in another process (tests/peers/vehicle_sim.py, playing
ArduPilot SITL's side over MAVLink on 127.0.0.1). The vehicle flies a
scripted flight, streams SIM_STATE once asked for it, and receives our
ODOMETRY; the feed must match the vehicle's truth as closely as the tracker
replays the same flight, at the camera's rate.

Small images and a grid to match (320x240, NI-SLAM's grid 240x180 instead
of 480x360: a quarter of the tracker's work) and a 20 Hz camera, so that
the loop keeps pace on this shared 2-core machine while others run (at 30 Hz
a full suite beside five other jobs, load 10, fell to 11 Hz; at 20 Hz the
same load held 20.0 Hz, ATE 3.3 / 12.9 mm).
Replay accuracy of the same flights with this profile (`nislam sim F
--seconds 5.5 --width 320 --height 240`, then `nislam replay --config` with
the grid, perfect AHRS, 2026-11-25): circle 3.1 mm, aggressive 9.4 mm ATE
RMSE (default grid: 1.2 and 11.7 mm). One rendering is one sample of a
spread: over render seeds 0-7 (2026-11-28) the same replays read circle
3.0-6.8 mm and aggressive 5.9-25.6 mm, and the closed loop, whose frames
fall at other instants each run, reads anywhere in it (circle 3.1-7.6 mm).
So the feed is held to the tracker's own poses (the service scores the same
frames against the rendered camera's truth: a wrong stamp, frame or axis
between the tracker and the vehicle shows as a difference), and circle's
ATE bar sits about 1.5x above the replays' spread.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from subproc import REPO, JsonLinesProcess, free_port, python_script

from onboard.core.evaluation import umeyama_se3
from sim_replay.flights import Flight, scenario

NISLAM = REPO / ".venv" / "bin" / "nislam"
VEHICLE = REPO / "tests" / "peers" / "vehicle_sim.py"
FLIGHT_S, HOVER_S = 5.0, 1.5
# 20 Hz, not the camera's 30: the loop must keep pace on a shared CI machine
# whatever else runs; the rate itself is benchmarked (docs/closed_loop.md).
CAMERA_HZ = 20.0
# circle: ~1.5x the replays' spread above; aggressive (the loop's flight is
# gentler than the replay's 5.5 s: 4.0-4.5 mm in four runs) as before
ATE_BAR_M = {"circle": 0.010, "aggressive": 0.020}
PROFILE = """[mavlink]
state_dir = "{state}"
[nislam]
grid_width = 240
grid_height = 180
[sim_follow]
camera_hz = {camera_hz}
width = 320
height = 240
start_height_m = 1.3
[service]
stats_period_s = 1.0
"""


def fly(flight: str, tmp_path: Path) -> tuple[list[dict], float, dict]:
    """The vehicle flies `flight` with the service in the loop; returns the
    ODOMETRY it received, the monotonic time of the flight's t = 0, and the
    service's metrics."""
    port = free_port()
    vehicle = JsonLinesProcess(python_script(
        VEHICLE, f"udpin:127.0.0.1:{port}", "--flight", flight, "--seconds", str(FLIGHT_S),
        "--hover-s", str(HOVER_S)))
    vehicle.wait_for(lambda ls: any(m.get("ready") for m in ls), 60, "vehicle ready")
    cfg = tmp_path / f"{flight}.toml"
    cfg.write_text(PROFILE.format(state=tmp_path / "state", camera_hz=CAMERA_HZ))
    out = tmp_path / flight
    svc = JsonLinesProcess([str(NISLAM), "run", "--sim-follow", flight, "--mavlink",
                            f"udpout:127.0.0.1:{port}", "--config", str(cfg), "--out", str(out)])
    try:
        vehicle.wait_for(lambda ls: any(m.get("done") for m in ls), 120, "the flight")
    finally:
        rc = svc.stop()
        vehicle.stop()
    assert rc == 0, svc.stderr[-2000:]
    start = next(m["flight_start"] for m in vehicle.lines if "flight_start" in m)
    odometry = [m for m in vehicle.lines if m.get("mavpackettype") == "ODOMETRY"]
    return odometry, start, json.loads((out / "metrics.json").read_text())


@pytest.mark.parametrize("flight", ["circle", "aggressive"])
def test_the_feed_follows_the_vehicle_it_steers(flight: str, tmp_path: Path) -> None:
    odometry, start, metrics = fly(flight, tmp_path)
    t = np.array([m["time_usec"] * 1e-6 for m in odometry])
    during = (t >= start) & (t <= start + FLIGHT_S)
    # The feed's rate while the vehicle flies: the camera's rate, less what
    # the renderer or this (shared, loaded) machine dropped.
    hz = during.sum() / FLIGHT_S
    # Capture on our clock -> received by the vehicle on the same clock.
    latency_ms = np.array([m["t"] - m["time_usec"] * 1e-6 for m in odometry]) * 1e3
    # Truth: the flight's body position (the camera sits at the body origin)
    # at each capture time; the feed's world starts at its first pose.
    body = Flight(scenario(flight))
    truth = body.position(np.clip(t - start, None, FLIGHT_S))
    est = np.array([[m["x"], m["y"], m["z"]] for m in odometry])
    R, tr = umeyama_se3(est, truth)
    err = np.linalg.norm(est @ R.T + tr - truth, axis=1)
    ate = float(np.sqrt(np.mean(err**2)))
    p50, p99 = np.percentile(latency_ms, [50, 99])
    print(f"{flight}: {len(odometry)} poses, {hz:.1f} Hz in flight, ATE {ate * 1e3:.1f} mm "
          f"(service's own score {metrics['ate_rmse_m'] * 1e3:.1f} mm over "
          f"{metrics['frames_evaluated']} frames), latency capture -> vehicle p50 {p50:.1f} ms, "
          f"p99 {p99:.1f} ms; late frames {metrics['skipped']['late_frames']}; render "
          f"{metrics['source_stats']['render_ms_median']:.1f} ms median")
    assert len({m["reset_counter"] for m in odometry}) == 1
    assert hz >= 0.8 * CAMERA_HZ
    assert ate <= ATE_BAR_M[flight]
    assert (latency_ms > 0).all() and p50 < 100.0
    # The service scored the same poses against the rendered camera's truth;
    # the vehicle's truth at the ODOMETRY's stamps must agree (6 runs:
    # within 0.2 mm).
    own = metrics["ate_rmse_m"]
    assert abs(ate - own) <= 1e-3 + 0.15 * own
    src = metrics["source_stats"]
    assert src["frames_rendered"] >= len(odometry) and src["vehicle_states"] > 40 * FLIGHT_S
    # Moved as flown: the feed spans the flight, not a hover.
    assert np.ptp(est[:, :2], axis=0).max() > 0.5


def test_the_vehicles_start_becomes_the_ekf_origin(tmp_path: Path) -> None:
    """Without [mavlink] set_origin the vehicle's first reported position is
    offered as the EKF origin, until the autopilot confirms it."""
    port = free_port()
    vehicle = JsonLinesProcess(python_script(
        VEHICLE, f"udpin:127.0.0.1:{port}", "--flight", "circle", "--seconds", "0.5"))
    vehicle.wait_for(lambda ls: any(m.get("ready") for m in ls), 60, "vehicle ready")
    cfg = tmp_path / "origin.toml"
    cfg.write_text(PROFILE.format(state=tmp_path / "state", camera_hz=CAMERA_HZ))
    svc = JsonLinesProcess([str(NISLAM), "run", "--sim-follow", "circle", "--mavlink",
                            f"udpout:127.0.0.1:{port}", "--config", str(cfg),
                            "--out", str(tmp_path / "out")])
    try:
        vehicle.wait_for(lambda ls: any(m.get("mavpackettype") == "SET_GPS_GLOBAL_ORIGIN"
                                        for m in ls), 120, "the origin")
        vehicle.wait_for(lambda ls: any(m.get("done") for m in ls), 120, "the flight")
    finally:
        assert svc.stop() == 0, svc.stderr[-2000:]
        vehicle.stop()
    origins = [m for m in vehicle.lines if m.get("mavpackettype") == "SET_GPS_GLOBAL_ORIGIN"]
    assert len(origins) == 1  # confirmed at once: not repeated
    o = origins[0]
    # vehicle_sim.py starts at ArduPilot's CMAC home (lat/lon degE7, alt mm)
    assert (o["latitude"], o["longitude"]) == (-353632621, 1491652374)
    assert abs(o["altitude"] - 584000) <= 1


@pytest.mark.parametrize("argv, says", [
    (["--sim-follow", "room"], "--sim-follow needs the simulator's MAVLink link"),
    (["--sim-follow", "garage", "--mavlink", "udpout:127.0.0.1:9"], "unknown scene or flight"),
    (["--sim-follow", "room", "--mavlink", "udpout:127.0.0.1:9", "--camera-size", "640"],
     "--camera-size must look like 640x480"),
    (["--sim-follow", "room", "--mavlink", "udpout:127.0.0.1:9", "--ahrs-profile", "gyro"],
     "sim_follow.ahrs_profile"),
    (["--sim", "hover", "--ahrs-profile", "myahrs"], "go with --sim-follow"),
])
def test_sim_follow_refuses_bad_use_with_one_line(argv: list[str], says: str) -> None:
    proc = subprocess.run([str(NISLAM), "run", *argv], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.count("\n") == 1 and says in proc.stderr, proc.stderr
