"""`sim_replay.sim.simulate`: the written recording, read back by the reader,
agrees with the flight it came from; conventions agree end to end."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from onboard import NislamError
from onboard.core.rotations import mount_rotation
from sim_replay.attitude import AttitudeErrorModel, attitude_for_replay, recorded_noise_deg
from sim_replay.flights import Flight, scenario
from sim_replay.render import Renderer
from sim_replay.scene import make_scene
from sim_replay.sim import SIM_MANIFEST, SimOptions, sim_options, simulate
from sim_replay.tum import open_sequence

# Small images and 1 cm texels: these tests check geometry, files and models,
# and a coarse texture builds ten times faster.
SMALL = {"width": 320, "height": 240, "texel_m": 0.01}


def _sim(tmp: Path, name: str = "circle", **kw) -> Path:
    opts = sim_options(**{"seconds": 1.0, **SMALL, **kw})
    simulate(name, tmp, opts, progress=False)
    return tmp


@pytest.fixture(scope="module")
def ideal(tmp_path_factory) -> Path:
    """1 s of the circle with an ideal camera and a perfect AHRS."""
    return _sim(tmp_path_factory.mktemp("ideal"), ideal_camera=True, seed=7)


def _digest(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p.name != SIM_MANIFEST:  # the manifest holds timings
            h.update(p.relative_to(folder).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def test_recording_reads_back_with_exact_groundtruth(ideal):
    seq = open_sequence(ideal)
    assert len(seq) == 30 and seq.skipped.total == 0 and seq.skipped.noticed == 0
    cam = seq.camera
    assert (cam.width, cam.height, cam.depth_scale) == (320, 240, 5000.0)
    assert np.allclose(cam.q_B_C_xyzw, [0.5, 0.5, 0.5, 0.5])  # the forward mount
    assert np.allclose(np.diff(seq.frame_times_s), 1 / 30.0, atol=2e-6)
    # Ground truth is the flight's camera pose at the written stamps.
    flight = Flight(scenario("circle"))
    p, r_w_b = flight.body_pose(seq.frame_times_s - 1000.0)
    gt = seq.groundtruth
    assert np.allclose(gt.t_s, seq.frame_times_s, atol=1e-9)
    assert np.abs(gt.p_xyz_m - p).max() < 1e-6
    r_w_c = r_w_b @ mount_rotation("forward")
    ang = (Rotation.from_quat(gt.q_xyzw).inv() * Rotation.from_matrix(r_w_c)).magnitude()
    assert ang.max() < 1e-8
    # Depth PNGs hold the rendered depth to the PNG's quantisation (0.2 mm).
    frames = seq.load_all(max_frames=3)
    renderer = Renderer(make_scene("room"), seq.intrinsics, seed=7, texel_m=0.01)
    view = renderer.render(r_w_c[2], p[2])
    assert np.abs(frames[2].depth_m - view.depth_m).max() <= 0.5 / 5000.0 + 1e-6
    assert np.array_equal(frames[2].bgr, view.bgr)


def test_attitude_file_gives_the_camera_rotation_at_frame_times(ideal):
    """attitude.txt holds the body orientation at the AHRS's own stamps; the
    reader turns it into the camera's with q_B_C from camera.toml. With the
    error model at zero that is the ground-truth camera rotation, up to
    interpolating between 100 Hz samples."""
    seq = open_sequence(ideal)
    series, label = attitude_for_replay(seq, AttitudeErrorModel())
    assert label.startswith("attitude.txt")
    t_att = seq.attitude.t_s
    assert not np.isin(np.round(t_att, 6), np.round(seq.frame_times_s, 6)).any()  # own clock
    r_att, ok = series.rotations_at(seq.frame_times_s)
    assert ok.all()
    r_gt = Rotation.from_quat(seq.groundtruth.q_xyzw)
    err_deg = np.degrees((r_gt.inv() * Rotation.from_matrix(r_att)).magnitude())
    assert err_deg.max() < 0.005, err_deg.max()  # slerp across 10 ms at <= 26 deg/s


def test_attitude_errors_in_the_recording_match_the_model(tmp_path):
    seq_dir = _sim(tmp_path / "noisy", "hover", seconds=10.0, attitude_noise_deg=0.5,
                   attitude_offset_ms=20.0, attitude_dropout=0.1, width=64, height=48,
                   camera_hz=3.0)
    seq = open_sequence(seq_dir)
    att = seq.attitude
    flight = Flight(scenario("hover"))
    truth = Rotation.from_matrix(flight.R_W_B(att.t_s - 1000.0 - 0.020))
    err = np.degrees((truth.inv() * Rotation.from_quat(att.q_xyzw)).as_rotvec())
    assert np.all(np.abs(err.std(axis=0) / 0.5 - 1.0) < 0.1), err.std(axis=0)
    expected_samples = (10.0 + 2 * 0.15) * 100
    assert abs(len(att) / expected_samples - 0.9) < 0.03  # 10 % dropout
    # The sim's AHRS errors are the same model the replay applies.
    manifest = json.loads((seq_dir / SIM_MANIFEST).read_text())
    assert manifest["options"]["ahrs"]["errors"]["noise_deg"] == 0.5


def test_same_seed_same_recording_other_seed_other_one(tmp_path):
    tiny = {"seconds": 0.3, "width": 96, "height": 72}
    a = _digest(_sim(tmp_path / "a", "figure8", seed=1, **tiny))
    b = _digest(_sim(tmp_path / "b", "figure8", seed=1, **tiny))
    c = _digest(_sim(tmp_path / "c", "figure8", seed=2, **tiny))
    assert a == b and a != c


def test_output_folder_policy(tmp_path):
    out = _sim(tmp_path / "run", "hover", seconds=0.2, width=64, height=48)
    (out / "replay").mkdir()
    (out / "notes.md").write_text("mine")
    stale = out / "rgb" / "stale.png"
    stale.write_bytes(b"old")
    _sim(out, "hover", seconds=0.1, width=64, height=48)  # over our own recording: fine
    assert (out / "replay").is_dir() and (out / "notes.md").read_text() == "mine"
    assert not stale.exists() and len(open_sequence(out)) == 3
    # A folder holding somebody else's recording is never cleared.
    foreign = tmp_path / "recorded"
    foreign.mkdir()
    (foreign / "rgb.txt").write_text("1.0 rgb/1.png\n")
    with pytest.raises(NislamError, match="not written by nislam sim"):
        _sim(foreign, "hover", seconds=0.1, width=64, height=48)
    assert (foreign / "rgb.txt").read_text() == "1.0 rgb/1.png\n"


def test_bad_options_are_clear_errors(tmp_path):
    with pytest.raises(NislamError, match="--seconds"):
        SimOptions(seconds=0.0)
    with pytest.raises(NislamError, match="unknown scenario"):
        simulate("barrel-roll", tmp_path / "x", SimOptions(seconds=1.0), progress=False)
    assert not (tmp_path / "x").exists()


def test_down_mount_sees_the_floor(tmp_path):
    seq = open_sequence(_sim(tmp_path / "down", "hover", seconds=0.1, mount="down",
                             ideal_camera=True, width=64, height=48))
    frame = seq.load_all(1)[0]
    # 1.2 m above the floor, the drone barely tilted: depth ~1.2 m everywhere.
    assert np.allclose(np.median(frame.depth_m), 1.2, atol=0.05)
    assert cv2.countNonZero((frame.depth_m > 0).astype(np.uint8)) == 64 * 48


def test_sim_with_faults_writes_the_damaged_flight(tmp_path):
    out = tmp_path / "direct"
    result = simulate("hover", out, SimOptions(seconds=1.5, width=64, height=48, texel_m=0.01),
                      faults="zero-depth:1,att-nan:2", progress=False)
    assert result.faults["expected"] == {"empty_depth_frames": 1, "attitude_nan_samples": 2}
    assert "faults      zero-depth:1,att-nan:2: empty_depth_frames +1" in "\n".join(
        result.summary_lines())
    assert (out / SIM_MANIFEST).is_file() and (out / "faults.json").is_file()
    assert not list(tmp_path.glob(".direct.clean.*"))  # the clean render is removed
    seq = open_sequence(out)
    assert len(list(seq)) == 44 and seq.skipped.empty_depth_frames == 1
    assert seq.skipped.attitude_nan_samples == 2


def test_the_replay_averages_the_attitude_noise_the_flight_states(tmp_path):
    """A flight whose sim.json states 0.3 deg of white AHRS noise: the replay's
    attitude widens its fit against that noise (attitude_smoothing.adaptive_fit)
    and lands closer to the true camera rotation at the frames than the fixed
    +-40 ms fit; a flight that states no noise gets the fixed fit, bit for bit."""
    seq = open_sequence(_sim(tmp_path / "noisy", "circle", seconds=4.0, attitude_noise_deg=0.3,
                             width=64, height=48, camera_hz=10.0, seed=3))
    r_gt = Rotation.from_quat(seq.groundtruth.q_xyzw)
    frames = seq.frame_times_s[5:-5]  # a full window on both sides

    def err_deg(smoothing_max_s: float) -> float:
        series, _ = attitude_for_replay(seq, AttitudeErrorModel(), smoothing_max_s=smoothing_max_s)
        got = Rotation.from_matrix(np.stack([series.rotation_at(t) for t in frames]))
        return float(np.degrees(np.sqrt(np.mean((r_gt[5:-5].inv() * got).magnitude() ** 2))))

    widened, fixed = err_deg(0.1), err_deg(0.04)
    assert widened < 0.8 * fixed, (widened, fixed)

    exact = open_sequence(_sim(tmp_path / "exact", "circle", seconds=1.0, width=64, height=48,
                               camera_hz=10.0, seed=3))
    a, _ = attitude_for_replay(exact, AttitudeErrorModel(), ahrs_noise_deg=0.1)
    b, _ = attitude_for_replay(exact, AttitudeErrorModel(), smoothing_max_s=0.04)
    assert all(np.array_equal(a.rotation_at(t), b.rotation_at(t)) for t in exact.frame_times_s[2:-2])


def test_the_attitude_noise_a_replay_assumes(tmp_path):
    """sim_replay.attitude.recorded_noise_deg: a simulated flight's own figure;
    a real AHRS's recording (attitude.txt, no sim.json) the configured one, as
    the live buffer takes it; ground truth (no attitude.txt) none."""
    flight = _sim(tmp_path / "f", "hover", seconds=0.5, attitude_noise_deg=0.2, width=64,
                  height=48, camera_hz=10.0)
    assert recorded_noise_deg(open_sequence(flight), 0.1) == pytest.approx(0.2)
    (flight / "sim.json").unlink()
    assert recorded_noise_deg(open_sequence(flight), 0.1) == 0.1
    (flight / "attitude.txt").unlink()
    assert recorded_noise_deg(open_sequence(flight), 0.1) == 0.0
