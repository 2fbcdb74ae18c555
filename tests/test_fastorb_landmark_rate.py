"""FastORB's new landmarks on a rolling-shutter camera, settled with the
body rate of the poses on both sides of the frame that made them
(onboard/fastorb/landmark_rate.py, docs/fastorb_backend.md "Landmarks
settled with the poses' rate")."""

from __future__ import annotations

import numpy as np

from onboard.core.se3 import se3_exp
from onboard.fastorb.landmark_rate import central_rate, settle, unsettled
from onboard.fastorb.shutter import points_at_mid

K = np.array([[517.3, 0.0, 318.6], [0.0, 516.5, 255.3], [0.0, 0.0, 1.0]])
H = 480
READOUT = 0.028


def _made(uv, z, omega, rho, T_cw):
    """World landmarks as the tracker makes them (keyframing._landmarks)."""
    p_C = points_at_mid(uv, z, K, np.concatenate([omega, rho]), READOUT, H)
    return (p_C - T_cw[:3, 3]) @ T_cw[:3, :3]


def test_settled_landmarks_equal_those_made_with_the_new_rate() -> None:
    """The move `settle` gives takes landmarks made with one rate exactly to
    those made with another (p_mid is linear in the rate); a wrong sign, axis
    or frame (camera vs world) leaves them millimetres off."""
    rng = np.random.default_rng(4)
    uv = rng.uniform([0, 0], [640, 480], (300, 2))
    z = rng.uniform(0.6, 3.5, 300)
    T_cw = se3_exp(np.array([0.3, -0.5, 0.2, 0.4, -0.1, 0.3]))
    rho = np.array([0.1, -0.2, 0.05])
    shear_rate = np.array([-0.4, 0.9, 0.6])  # what the rows' shear said
    true_rate = np.array([0.2, 1.1, -0.3])
    before = _made(uv, z, shear_rate, rho, T_cw)
    want = _made(uv, z, true_rate, rho, T_cw)
    assert np.abs(before - want).max() > 5e-3  # the error to undo: several mm
    u = unsettled(np.arange(300), uv, z, K, shear_rate, READOUT, H, T_cw, 1.0, np.eye(4), 0.9)
    np.testing.assert_allclose(before + settle(u, true_rate), want, atol=1e-12)
    np.testing.assert_array_equal(settle(u, shear_rate), 0.0)


def test_central_rate_is_the_rate_between_the_poses_on_both_sides() -> None:
    """A camera turning at a constant body rate: the poses one frame before
    and after give that rate (camera axes, rad/s), whatever the pose between."""
    xi = np.array([0.5, -1.2, 0.8, 0.2, 0.1, -0.3])  # per second
    dt = 1 / 30
    T_prev = se3_exp(np.array([0.1, 0.2, -0.3, 0.5, 0.0, 1.0]))
    T_now = se3_exp(dt * xi) @ T_prev
    T_next = se3_exp(dt * xi) @ T_now
    u = unsettled(np.arange(1), np.zeros((1, 2)), np.ones(1), K, np.zeros(3), READOUT, H,
                  T_now, dt, T_prev, 0.0)
    np.testing.assert_allclose(central_rate(u, T_next, 2 * dt), xi[:3], atol=1e-9)


# ------------------------------------------------- the tracker on a rolling shutter
def _rs_render(room, pose_at, t_mid: float, band: int = 16):
    """A rolling-shutter frame: rows read out top first over READOUT, each
    band of `band` rows rendered at its own instant (pose_at(t) -> (R, c))."""
    rays = room._rays_C
    bgr = np.zeros((H, rays.shape[1], 3), np.uint8)
    depth = np.zeros((H, rays.shape[1]), np.float32)
    try:
        for r0 in range(0, H, band):
            room._rays_C = rays[r0:r0 + band]
            t = t_mid + READOUT * ((r0 + 0.5 * band - 0.5) / H - 0.5)
            bgr[r0:r0 + band], depth[r0:r0 + band] = room.render(*pose_at(t))
    finally:
        room._rays_C = rays
    return bgr, depth


def _turn(t: float):
    """(R_W_C, c_W) turning at up to ~1.2 rad/s about a tilted axis from rest
    (no motion at t = 0, so the first key frame's landmarks are exact)."""
    from scipy.spatial.transform import Rotation

    angle = 0.25 * (1.0 - np.cos(4.0 * t))  # rad; rate 1 sin(4t) rad/s
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    c = np.array([0.05 * np.sin(2.0 * t), 0.0, 0.03 * t])
    return Rotation.from_rotvec(angle * axis).as_matrix(), c


def _camera_errors(tracker, room) -> np.ndarray:
    """(N,) mm: each key frame's own new landmarks (those no earlier key frame
    has) in that key frame's estimated camera axes, against the point its
    pixel truly saw, in its true camera axes at the middle row's instant."""
    errs, seen = [], set()
    for kf in tracker._map.keyframes():
        fresh = np.array([i not in seen for i in kf.ids.tolist()])
        seen.update(kf.ids.tolist())
        if kf.keyframe_id == 0 or not fresh.any():
            continue
        uv, X = kf.uv[fresh], kf.xyz_W[fresh]
        p_est = X @ kf.T_cw[:3, :3].T + kf.T_cw[:3, 3]
        R_mid, c_mid = _turn(kf.t_s)
        tau = READOUT * (uv[:, 1] / H - 0.5)
        for (u, v), t, pe in zip(uv, tau, p_est):
            R, c = _turn(kf.t_s + t)
            ray = np.array([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], 1.0])
            X_true = c + _depth_along(room, R @ ray, c) * (R @ ray)
            p_true = R_mid.T @ (X_true - c_mid)
            errs.append(1e3 * np.linalg.norm(pe - p_true))
    return np.array(errs)


def _depth_along(room, ray_W, c_W) -> float:
    """Distance along `ray_W` (camera z = 1) to the nearest plane of the room."""
    best = np.inf
    for pl in room.planes:
        n = np.cross(pl.u, pl.v)
        den = ray_W @ n
        if abs(den) < 1e-12:
            continue
        s = ((pl.origin - c_W) @ n) / den
        a = (c_W - pl.origin) @ pl.u + s * (ray_W @ pl.u)
        b = (c_W - pl.origin) @ pl.v + s * (ray_W @ pl.v)
        if s > 0.05 and s < best and (pl.size_m is None or (
                0 <= a <= pl.size_m[0] and 0 <= b <= pl.size_m[1])):
            best = s
    return best


def test_settled_landmarks_sit_where_the_rolling_shutter_saw_them() -> None:
    """A camera turning at up to 1 rad/s with a 28 ms rolling shutter: the
    key frames' new landmarks, settled with the poses' rate one frame later,
    lie closer to the points their pixels saw than when made with the rate
    the frame's own rows' shear gave (the tracker's estimate, in its camera);
    loop closing's records of the key frames follow them."""
    from test_fastorb import DT, INTR, NoAttitude, Room

    from onboard.core.messages import RgbdFrame
    from onboard.fastorb.params import FastOrbParams
    from onboard.fastorb.tracker import FastOrbTracker

    room = Room(seed=5)
    frames = [RgbdFrame(k * DT, *_rs_render(room, _turn, k * DT)) for k in range(14)]
    out = {}
    for settle_on in (False, True):
        # Loop closing on, for its records; it queries only in backend_step(), never run here.
        params = FastOrbParams(rolling_shutter_readout_s=READOUT, keyframe_max_frames=3,
                               rolling_shutter_settle_landmarks=settle_on)
        tr = FastOrbTracker(INTR, params)
        tracked = sum(tr.track(f, NoAttitude()).trusted for f in frames)
        tr.finish_frame()
        assert tracked == len(frames)
        out[settle_on] = _camera_errors(tr, room)
        for kf in tr._map.keyframes():  # loop closing's records follow the moved landmarks
            rec = tr.loops._records[tr.loops._index[kf.keyframe_id]]
            np.testing.assert_allclose(rec.p_C, kf.xyz_W @ kf.T_cw[:3, :3].T + kf.T_cw[:3, 3],
                                       atol=1e-12)
    rms = {k: float(np.sqrt(np.mean(v**2))) for k, v in out.items()}
    assert len(out[True]) > 200
    assert rms[True] < 0.8 * rms[False], rms


def _seen(p_mid: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """Camera points as the rows saw them (the inverse of points_at_mid):
    p_v with p_v - tau_v (omega x p_v + rho) = p_mid, tau_v from p_v's own row."""
    p = p_mid.copy()
    for _ in range(20):
        tau = READOUT * ((K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]) / H - 0.5)
        p = p_mid + tau[:, None] * (np.cross(xi[:3], p) + xi[3:])
    return p


def test_a_key_frame_reposed_with_the_settled_rate_puts_its_landmarks_right() -> None:
    """reposed_moves: the frame's pose solved again on its inliers' raw
    pixels with the settled rate, and its new landmarks made from that pose,
    land on the truth (the model is exact here) from a pose and a rate that
    were both off (what the shear fit gave); `settle` alone keeps the pose's
    error, and a re-pose with the old rate keeps both."""
    from dataclasses import replace

    from onboard.fastorb.landmark_rate import reposed_moves

    rng = np.random.default_rng(6)
    T = se3_exp(np.array([0.2, -0.3, 0.1, 0.1, 0.05, -0.2]))
    xi = np.array([0.4, -1.0, 0.6, 0.05, -0.03, 0.02])  # the true twist per second

    def frame(n):  # world points, their raw pixels and depths under T, xi
        p_mid = np.c_[rng.uniform(-1.2, 1.2, (n, 2)), rng.uniform(1.0, 3.0, n)]
        p_v = _seen(p_mid, xi)
        uv = np.c_[K[0, 0] * p_v[:, 0] / p_v[:, 2] + K[0, 2], K[1, 1] * p_v[:, 1] / p_v[:, 2] + K[1, 2]]
        return (p_mid - T[:3, 3]) @ T[:3, :3], uv, p_v[:, 2], p_mid[:, 2]

    X_in, uv_in, _, z_in = frame(300)  # the disparity of the point at the middle row's instant
    X_new, uv_new, z_new, _ = frame(200)
    T_fit = se3_exp(np.array([0.004, -0.003, 0.002, 0.006, -0.004, 0.003])) @ T  # ~4 mm, 0.3 deg off
    omega_fit = xi[:3] + np.array([0.3, -0.2, 0.25])
    u = unsettled(np.arange(200), uv_new, z_new, K, omega_fit, READOUT, H, T_fit, 1.0,
                  np.eye(4), 0.9)
    u = replace(u, inliers=(uv_in, X_in, 120.0 / z_in, xi[3:].copy()))
    made = _made(uv_new, z_new, omega_fit, xi[3:], T_fit)

    def err(moves):
        return np.abs(made + moves - X_new).max()

    assert err(reposed_moves(u, xi[:3], K, READOUT, H, 1.0, 120.0)) < 1e-5
    assert err(settle(u, xi[:3])) > 3e-3  # the fit's pose error stays
    assert err(reposed_moves(u, omega_fit, K, READOUT, H, 1.0, 120.0)) > 1e-3
