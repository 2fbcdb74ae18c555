"""The closed-loop sensors' pure parts (sim_replay/follow_state.py,
sim_replay/follow.py): simulator messages, placing the vehicle in the scene,
smoothing lat/lon steps, predicting the pose, the AHRS error stream."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from onboard import NislamError
from sim_replay.attitude import AttitudeErrorModel
from sim_replay.follow import FollowAhrs, start_of
from sim_replay.follow_state import M_PER_DEG_E7, VehicleTrack, state_from_message
from sim_replay.sensors import AhrsModel

LAT0, LON0, ALT0 = -353632621, 1491652374, 584.0
LON_SCALE = math.cos(math.radians(LAT0 * 1e-7))


def sim_state(lat_e7: float, lon_e7: float, alt: float, *, v=(0.0, 0.0, 0.0), q=(1, 0, 0, 0),
              w=(0.0, 0.0, 0.0), ints: bool = True, degrees: bool = False) -> SimpleNamespace:
    lat = lat_e7 * 1e-7 if degrees else float(np.float32(lat_e7))
    lon = lon_e7 * 1e-7 if degrees else float(np.float32(lon_e7))
    return SimpleNamespace(
        get_type=lambda: "SIM_STATE", q1=q[0], q2=q[1], q3=q[2], q4=q[3],
        xgyro=w[0], ygyro=w[1], zgyro=w[2], lat=lat, lon=lon, alt=alt,
        vn=v[0], ve=v[1], vd=v[2],
        lat_int=int(round(lat_e7)) if ints else 0, lon_int=int(round(lon_e7)) if ints else 0)


def at_ned(n: float, e: float, d: float, **kw) -> SimpleNamespace:
    return sim_state(LAT0 + n / M_PER_DEG_E7, LON0 + e / (M_PER_DEG_E7 * LON_SCALE), ALT0 - d,
                     **kw)


def test_sim_state_position_forms() -> None:
    s = state_from_message(sim_state(LAT0, LON0, ALT0), 5)
    assert s is not None and s.fine and (s.lat_e7, s.lon_e7) == (LAT0, LON0) and s.t_ns == 5
    # ArduPilot without lat_int: degE7 in a float32 (coarse); common.xml: degrees.
    coarse = state_from_message(sim_state(LAT0, LON0, ALT0, ints=False), 0)
    assert not coarse.fine and abs(coarse.lat_e7 - LAT0) < 32
    deg = state_from_message(sim_state(LAT0, LON0, ALT0, ints=False, degrees=True), 0)
    assert abs(deg.lat_e7 - LAT0) < 200 and abs(deg.lon_e7 - LON0) < 200
    q = Rotation.from_euler("z", 30, degrees=True).as_quat()  # x, y, z, w
    s = state_from_message(sim_state(LAT0, LON0, ALT0, q=(q[3], q[0], q[1], q[2])), 0)
    assert np.allclose(s.q_N_B_xyzw, q)
    assert state_from_message(sim_state(LAT0, LON0, math.nan), 0) is None
    assert state_from_message(sim_state(LAT0, LON0, ALT0, q=(0.5, 0, 0, 0)), 0) is None
    assert state_from_message(SimpleNamespace(get_type=lambda: "HEARTBEAT"), 0) is None


def test_hil_state_quaternion_units() -> None:
    msg = SimpleNamespace(get_type=lambda: "HIL_STATE_QUATERNION", attitude_quaternion=[1, 0, 0, 0],
                          rollspeed=0.1, pitchspeed=0.2, yawspeed=0.3, lat=LAT0, lon=LON0,
                          alt=584123, vx=150, vy=-20, vz=5)
    s = state_from_message(msg, 0)
    assert s.alt_m == pytest.approx(584.123) and np.allclose(s.v_N_m_s, [1.5, -0.2, 0.05])
    assert np.allclose(s.w_B_rad_s, [0.1, 0.2, 0.3])


def test_first_state_is_placed_at_the_scene_start_and_moves_as_reported() -> None:
    start = np.array([0.0, -0.4, -0.1])
    track = VehicleTrack(start)
    track.push_message(at_ned(10.0, 20.0, -3.0), 0)  # anywhere: that point is the start
    assert np.allclose(track.pose_at(0).p_W_m, start)
    track.push_message(at_ned(10.5, 19.0, -4.0), int(1e9))  # a report 1 s later, no velocity
    assert np.allclose(track.pose_at(int(1e9)).p_W_m, start + [0.5, -1.0, -1.0], atol=0.02)


def test_lat_lon_steps_are_smoothed_along_the_velocity() -> None:
    """1 m/s north-east at 50 Hz, positions on 1.1 cm steps: the filtered
    pose stays within a few mm of the truth; predictions in between too."""
    track = VehicleTrack(np.zeros(3), tau_s=0.5)
    v = np.array([0.8, 0.6, 0.0])
    errs = []
    for k in range(200):
        t = k * 0.02
        track.push_message(at_ned(*(v * t), v=v), int(t * 1e9))
        if k > 50:
            for dt in (0.0, 0.01):  # at a report and between two
                p = track.pose_at(int((t + dt) * 1e9)).p_W_m
                errs.append(np.linalg.norm(p - v * (t + dt)))
    assert max(errs) < 0.004
    # The raw reported positions err by up to half a step.
    assert track.pose_at(int(5e9)) is None  # the simulator went quiet for 1 s


def test_pose_rotates_with_the_body_rates_between_reports() -> None:
    track = VehicleTrack(np.zeros(3))
    track.push_message(at_ned(0, 0, 0, w=(0.0, 0.0, 1.0)), 0)
    R = track.pose_at(int(0.02e9)).R_W_B
    assert Rotation.from_matrix(R).as_euler("ZYX")[0] == pytest.approx(0.02)


def test_the_anchor_is_kept_for_the_next_process(tmp_path) -> None:
    f = tmp_path / "anchor.json"
    first = VehicleTrack(np.zeros(3), anchor_file=f)
    first.push_message(at_ned(0, 0, 0), 0)
    # Restarted while the vehicle hovers 1.2 m up and 2 m north: same room.
    again = VehicleTrack(np.zeros(3), anchor_file=f)
    again.push_message(at_ned(2.0, 0.0, -1.2), 0)
    assert np.allclose(again.pose_at(0).p_W_m, [2.0, 0.0, -1.2], atol=0.02)
    # A vehicle far away (another simulator home): a new anchor.
    far = VehicleTrack(np.zeros(3), anchor_file=f)
    far.push_message(at_ned(500.0, 0.0, 0.0), 0)
    assert np.allclose(far.pose_at(0).p_W_m, 0.0)


def test_scene_starts() -> None:
    scene, flight, p = start_of("room", 0.1)
    assert (scene, flight) == ("room", "circle") and np.allclose(p, [0.0, -0.4, -0.1])
    scene, flight, p = start_of("aggressive", 1.3)
    assert scene == "room" and np.allclose(p, [0.0, -1.2, -1.3])
    with pytest.raises(NislamError, match="unknown scene or flight"):
        start_of("garage", 0.1)


def test_simulated_ahrs_errors() -> None:
    track = VehicleTrack(np.zeros(3))
    q = Rotation.from_euler("ZYX", [40, 5, -3], degrees=True).as_quat()
    track.push_message(at_ned(0, 0, 0, q=(q[3], q[0], q[1], q[2])), 0)
    exact = FollowAhrs(track, lambda s: None, AhrsModel(100.0))
    got = exact._measure(int(0.01e9))
    assert np.allclose(got.q_W_B_xyzw, q, atol=1e-9) or np.allclose(got.q_W_B_xyzw, -q, atol=1e-9)
    noisy = FollowAhrs(track, lambda s: None,
                       AhrsModel(100.0, AttitudeErrorModel(noise_deg=0.5)), seed=1)
    errs = [(Rotation.from_quat(noisy._measure(k * 10**7).q_W_B_xyzw).inv()
             * Rotation.from_quat(q)).magnitude() for k in range(1, 40)]
    # |error| of 0.5 deg per axis: mean 0.5 * sqrt(8 / pi) = 0.8 deg
    assert 0.5 < math.degrees(float(np.mean(errs))) < 1.2
    dropping = FollowAhrs(track, lambda s: None, AhrsModel(100.0, dropout=0.5), seed=2)
    kept = sum(dropping._measure(k * 10**7) is not None for k in range(1, 41))
    assert 8 < kept < 32


def test_the_render_process_renders_what_the_thread_does() -> None:
    """`[sim_follow] render_process`: the same frame (bytes) from the worker
    process as from the in-thread renderer; the textures come from the cache
    (the session's, which the closed-loop services share)."""
    from onboard.app.sources import cache_directory
    from onboard.core.rotations import matrix_to_quat, mount_rotation
    from sim_replay.follow import FollowCamera, follow_camera_model

    cache = cache_directory()

    R_B_C = mount_rotation("forward")
    cam = follow_camera_model(160, 120, matrix_to_quat(R_B_C))
    track = VehicleTrack(np.array([0.0, -0.4, -1.3]))
    track.push_message(at_ned(0, 0, 0, q=(math.cos(0.4), 0, 0, math.sin(0.4))), 0)
    assert track.pose_at(0) is not None
    frames = []
    for separate in (False, True):
        camera = FollowCamera(track, "room", cam, R_B_C, texture_cache=cache,
                              separate_process=separate)
        try:
            camera._capture(0, 7)
        finally:
            camera.stop()
        got = camera.slot.take(0, 0.0)
        assert got is not None
        frames.append(got[1])
    assert list(cache.glob("textures-room-*.npz"))
    assert np.array_equal(frames[0].bgr, frames[1].bgr)
    assert np.array_equal(frames[0].depth_m, frames[1].depth_m)
    assert (frames[0].depth_m > 0).mean() > 0.5  # a real view of the room


def test_the_simulated_ahrs_catches_up_after_a_stall() -> None:
    """A stall (here: the sink blocks 0.3 s) delays samples, never drops
    them: a gap would leave the frames in it without attitude ("no
    attitude", a reset of the feed)."""
    import threading
    import time

    track = VehicleTrack(np.zeros(3))
    track.push_message(at_ned(0, 0, 0), time.monotonic_ns())
    stamps: list[int] = []
    done = threading.Event()

    def sink(sample) -> None:
        stamps.append(sample.t_ns)
        if len(stamps) == 5:
            time.sleep(0.3)
        if len(stamps) >= 60:
            done.set()

    # Keep the vehicle's state fresh (a state older than 0.5 s gives no pose).
    ahrs = FollowAhrs(track, sink, AhrsModel(100.0))
    ahrs.start()
    try:
        while not done.wait(0.05):
            track.push_message(at_ned(0, 0, 0), time.monotonic_ns())
    finally:
        ahrs.stop()
    gaps_ms = np.diff(stamps[:60]) * 1e-6
    assert gaps_ms.max() < 10.5 and gaps_ms.min() > 9.5  # every 10 ms, none missing
