"""The attitude at a frame fitted to the AHRS samples around it
(onboard/core/attitude_smoothing.py, used by the live buffer and the
replay's series alike): exact on a rotation with constant angular
acceleration, the per-sample jitter averaged, and the plain slerp wherever
the samples are too sparse to average (frame-time attitude, the newest
samples not in yet)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from onboard.core.attitude import AttitudeBuffer, AttitudeSample
from onboard.core.rotations import so3_log
from onboard.core.trajectory import Trajectory
from onboard.core.attitude_smoothing import without_widening
from sim_replay.attitude import AttitudeSeries

AXIS = np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])
R0 = Rotation.from_rotvec([0.2, 0.1, -0.3])
FRAMES = 0.5 + np.arange(30) / 30.0 + 0.0041  # between samples, like a camera's stamps


def truth(t) -> Rotation:
    """R_W_C(t) = R0 exp((1.5 t + 4 t^2) axis): 1.5 rad/s speeding up at 8 rad/s^2."""
    t = np.atleast_1d(np.asarray(t, dtype=np.float64))
    return R0 * Rotation.from_rotvec((1.5 * t + 4.0 * t**2)[:, None] * AXIS)


def samples(rate_hz: float, noise_deg: float = 0.0, seed: int = 0) -> Trajectory:
    t = np.arange(0.0, 2.0, 1.0 / rate_hz)
    r = truth(t)
    if noise_deg:
        rng = np.random.default_rng(seed)
        r = r * Rotation.from_rotvec(np.deg2rad(noise_deg) * rng.standard_normal((len(t), 3)))
    return Trajectory(t, np.zeros((len(t), 3)), r.as_quat())


def err_deg(r: np.ndarray, t: float) -> float:
    return float(np.rad2deg(np.linalg.norm(so3_log(truth(t)[0].as_matrix().T @ r))))


def test_exact_where_the_motion_is_quadratic():
    """No jitter: the fit has no bias on a constantly accelerating turn, and
    even removes the slerp's interpolation error between samples."""
    fit = AttitudeSeries(samples(100.0), smoothing_s=0.04)
    slerp = AttitudeSeries(samples(100.0), smoothing_s=0.0)
    assert max(err_deg(fit.rotation_at(t), t) for t in FRAMES) < 1e-6
    assert max(err_deg(slerp.rotation_at(t), t) for t in FRAMES) > 1e-4


def test_jitter_is_averaged():
    """0.1 deg of white jitter per 100 Hz sample: at the frames the fitted
    attitude's error is about half the slerp's (9 samples over +-40 ms:
    0.51 of one sample's sd, the slerp ~0.8)."""
    fit_e, slerp_e = [], []
    for seed in range(4):
        traj = samples(100.0, noise_deg=0.1, seed=seed)
        fit, slerp = AttitudeSeries(traj, smoothing_s=0.04), AttitudeSeries(traj, smoothing_s=0.0)
        fit_e += [err_deg(fit.rotation_at(t), t) for t in FRAMES]
        slerp_e += [err_deg(slerp.rotation_at(t), t) for t in FRAMES]
    ratio = np.sqrt(np.mean(np.square(fit_e)) / np.mean(np.square(slerp_e)))
    assert 0.45 < ratio < 0.8, ratio


def test_frame_time_attitude_is_the_slerp_bit_for_bit():
    """Samples 33 ms apart (the TUM replays' ground truth at frame times):
    too few to average, so the slerp between the neighbours."""
    traj = samples(30.0, noise_deg=0.5)
    fit, slerp = AttitudeSeries(traj, smoothing_s=0.04), AttitudeSeries(traj, smoothing_s=0.0)
    for t in FRAMES:
        assert np.array_equal(fit.rotation_at(t), slerp.rotation_at(t))


def _buffer(traj: Trajectory, r_b_c: Rotation, smoothing_s: float) -> AttitudeBuffer:
    buf = AttitudeBuffer(r_b_c.as_matrix(), capacity=4096, smoothing_s=smoothing_s)
    for t, q in zip(traj.t_s, traj.q_xyzw):
        q_w_b = (Rotation.from_quat(q) * r_b_c.inv()).as_quat()
        assert buf.push(AttitudeSample(int(round(t * 1e9)), tuple(q_w_b)))
    return buf


def test_the_live_buffer_fits_as_the_replay_does():
    """Body samples and a camera mount in the buffer, camera attitude in the
    series: the same fitted R_W_C."""
    traj = samples(100.0, noise_deg=0.1, seed=9)
    r_b_c = Rotation.from_euler("xyz", [90, 0, 90], degrees=True)
    buf, series = _buffer(traj, r_b_c, 0.04), AttitudeSeries(traj, smoothing_s=0.04)
    slerp = AttitudeSeries(traj, smoothing_s=0.0)
    for t in FRAMES[:8]:
        assert np.allclose(buf.rotation_at(t), series.rotation_at(t), atol=1e-9)
        assert not np.allclose(buf.rotation_at(t), slerp.rotation_at(t), atol=1e-6)


def test_a_gap_gives_no_attitude():
    traj = samples(100.0)
    keep = (traj.t_s < 1.0) | (traj.t_s > 1.3)  # an outage longer than max_gap_s
    gappy = AttitudeSeries(Trajectory(traj.t_s[keep], traj.p_xyz_m[keep], traj.q_xyzw[keep]),
                           smoothing_s=0.04)
    assert gappy.rotation_at(1.15) is None and gappy.rotation_at(0.5) is not None


@pytest.mark.parametrize("half_s", [0.03, 0.04])
def test_the_newest_samples_missing_fall_back_to_the_slerp(half_s):
    """Live, the samples after a frame may not be in yet: with one after it,
    the slerp (never a fit extrapolated beyond the samples)."""
    traj = samples(100.0, noise_deg=0.1)
    r_b_c = Rotation.identity()
    buf, slerp = _buffer(traj, r_b_c, half_s), _buffer(traj, r_b_c, 0.0)
    t = float(traj.t_s[-1]) - 0.005  # one sample after the frame
    assert np.array_equal(buf.rotation_at(t), slerp.rotation_at(t))
    t = float(traj.t_s[-1]) - 0.015  # two after it: fitted
    assert not np.array_equal(buf.rotation_at(t), slerp.rotation_at(t))


def wobble(t) -> Rotation:
    """A 4 Hz wobble of 8 deg about AXIS: no quadratic fits it over +-100 ms."""
    t = np.atleast_1d(np.asarray(t, dtype=np.float64))
    return R0 * Rotation.from_rotvec(np.deg2rad(8.0) * np.sin(2 * np.pi * 4.0 * t)[:, None] * AXIS)


def rms_err_deg(series, motion, times) -> float:
    e = [np.linalg.norm(so3_log(motion(t)[0].as_matrix().T @ series.rotation_at(t))) for t in times]
    return float(np.rad2deg(np.sqrt(np.mean(np.square(e)))))


def test_a_noisy_ahrs_gets_a_wider_window_where_the_motion_allows():
    """The ICI rule (attitude_smoothing.adaptive_fit): with the AHRS's white
    noise stated, a smooth turn is fitted over up to +-100 ms, which averages
    the jitter well below the fixed +-40 ms window's (21 samples against 9:
    about 0.33 of a sample's sd against 0.51)."""
    wide, fixed = [], []
    for seed in range(4):
        traj = samples(100.0, noise_deg=0.1, seed=seed)
        wide.append(rms_err_deg(AttitudeSeries(traj, smoothing_s=0.04, smoothing_max_s=0.1,
                                               noise_sd_deg=0.1), truth, FRAMES))
        fixed.append(rms_err_deg(AttitudeSeries(traj, smoothing_s=0.04), truth, FRAMES))
    assert np.mean(wide) < 0.8 * np.mean(fixed)


def test_the_window_stays_narrow_where_the_motion_bends():
    """On a 4 Hz wobble a +-100 ms quadratic is biased by far more than
    0.1 deg of jitter: the intervals part and the rule keeps near the +-40 ms
    fit (its bias may reach about ICI_GAMMA sd before the intervals part),
    where a fixed +-100 ms window errs several times as much."""
    traj = samples(100.0, noise_deg=0.1, seed=1)
    t = np.arange(0.0, 2.0, 0.01)
    traj = Trajectory(t, np.zeros((len(t), 3)),
                      (wobble(t) * Rotation.from_rotvec(np.deg2rad(0.1) * np.random.default_rng(1)
                                                        .standard_normal((len(t), 3)))).as_quat())
    adaptive = rms_err_deg(AttitudeSeries(traj, smoothing_s=0.04, smoothing_max_s=0.1,
                                          noise_sd_deg=0.1), wobble, FRAMES)
    fixed = rms_err_deg(AttitudeSeries(traj, smoothing_s=0.04), wobble, FRAMES)
    too_wide = rms_err_deg(AttitudeSeries(traj, smoothing_s=0.1), wobble, FRAMES)
    assert too_wide > 4.0 * fixed
    assert adaptive < 2.0 * fixed
    assert adaptive < 0.4 * too_wide


def test_without_a_stated_noise_nothing_widens():
    """An exact attitude (noise 0, the default) is fitted as before, to the bit;
    frame-time samples (TUM's ground truth) keep the slerp."""
    traj = samples(100.0, noise_deg=0.1, seed=2)
    a = AttitudeSeries(traj, smoothing_s=0.04, smoothing_max_s=0.1, noise_sd_deg=0.0)
    b = AttitudeSeries(traj, smoothing_s=0.04)
    assert all(np.array_equal(a.rotation_at(t), b.rotation_at(t)) for t in FRAMES)
    sparse = samples(30.0)
    c = AttitudeSeries(sparse, smoothing_s=0.04, smoothing_max_s=0.1, noise_sd_deg=0.0)
    d = AttitudeSeries(sparse, smoothing_s=0.0)
    assert all(np.array_equal(c.rotation_at(t), d.rotation_at(t)) for t in FRAMES)


def test_the_live_buffer_widens_as_the_replay_does():
    """AttitudeBuffer and AttitudeSeries share the rule: the same samples give
    the same attitude."""
    traj = samples(100.0, noise_deg=0.3, seed=3)
    series = AttitudeSeries(traj, smoothing_s=0.04, smoothing_max_s=0.1, noise_sd_deg=0.3)
    buf = AttitudeBuffer(smoothing_s=0.04, smoothing_max_s=0.1, noise_sd_deg=0.3)
    for t, q in zip(traj.t_s, traj.q_xyzw):
        buf.push(AttitudeSample(int(round(t * 1e9)), tuple(q)))
    for t in FRAMES:
        assert np.allclose(buf.rotation_at(t), series.rotation_at(t), atol=1e-9)


def test_a_consumer_can_keep_the_fixed_window():
    """without_widening: the look-ups of a widening source as with the fixed
    +-40 ms fit (the fused tracker's view, docs/fusion.md), for the replay's
    series and the live buffer alike; a source that does not widen is
    returned as it is."""
    traj = samples(100.0, noise_deg=0.1, seed=4)
    wide = AttitudeSeries(traj, smoothing_s=0.04, smoothing_max_s=0.1, noise_sd_deg=0.1)
    fixed = AttitudeSeries(traj, smoothing_s=0.04)
    buf = AttitudeBuffer(smoothing_s=0.04, smoothing_max_s=0.1, noise_sd_deg=0.1)
    for t, q in zip(traj.t_s, traj.q_xyzw):
        buf.push(AttitudeSample(int(round(t * 1e9)), tuple(q)))
    assert wide.widens and buf.widens and not fixed.widens
    assert not all(np.array_equal(wide.rotation_at(t), fixed.rotation_at(t)) for t in FRAMES)
    for source in (wide, buf):
        view = without_widening(source)
        assert all(np.allclose(view.rotation_at(t), fixed.rotation_at(t), atol=1e-12) for t in FRAMES)
    assert without_widening(fixed) is fixed


def test_the_fused_tracker_looks_the_attitude_up_without_widening():
    """Its trackers and its filter see the fixed fit: the fusion takes
    NI-SLAM's attitude error per frame as white."""
    from fake_results import track_result
    from onboard.core.messages import RgbdFrame
    from onboard.fusion.fused import FusedTracker

    seen = []

    class Spy:
        name = "nislam"

        def track(self, frame, attitude):
            seen.append(attitude.rotation_at(frame.t_s))
            return track_result(frame.t_s, trusted=False, lost_reason="spy")

        def finish(self):
            return None

    traj = samples(100.0, noise_deg=0.1, seed=5)
    wide = AttitudeSeries(traj, smoothing_s=0.04, smoothing_max_s=0.1, noise_sd_deg=0.1)
    fixed = AttitudeSeries(traj, smoothing_s=0.04)
    fused = FusedTracker([Spy()])
    img, depth = np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4), np.float32)
    for t in FRAMES[:5]:
        fused.track(RgbdFrame(t, img, depth), wide)
    assert all(np.array_equal(r, fixed.rotation_at(t)) for r, t in zip(seen, FRAMES[:5]))
