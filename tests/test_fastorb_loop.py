"""FastORB loop closing (onboard/fastorb/loop.py, place.py) on synthetic key
frames: landmarks with ORB-like descriptors seen from known poses, the poses
given to loop closing with a known drift."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from onboard.core.evaluation import umeyama_se3
from onboard.core.se3 import camera_in_world, inverse, make_pose
from onboard.fastorb.local_map import Keyframe, LocalMap
from onboard.fastorb.loop import LoopClosing, LoopSettings
from onboard.fastorb.place import KeyRecord, PlaceSettings, verify

FX, W, H = 500.0, 640, 480
K = np.array([[FX, 0, W / 2], [0, FX, H / 2], [0, 0, 1.0]])


def _camera(c_W: np.ndarray, yaw: float) -> np.ndarray:
    """T_cw of a level camera at c_W looking along (cos yaw, sin yaw, 0), z up."""
    fwd = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    R_W_C = np.stack([np.cross(down, fwd), down, fwd], axis=1)  # camera x, y, z in W
    return inverse(make_pose(R_W_C, c_W))


def _noisy(desc: np.ndarray, rng: np.random.Generator, bits: int = 6) -> np.ndarray:
    """The descriptors with `bits` random bits flipped each (a new view's ORB)."""
    out = desc.copy()
    for row in out:
        for b in rng.choice(256, bits, replace=False):
            row[b // 8] ^= np.uint8(1 << (b % 8))
    return out


def _keyframe(kf_id: int, T_true: np.ndarray, T_est: np.ndarray, xyz: np.ndarray,
              desc: np.ndarray, ids: np.ndarray, rng: np.random.Generator) -> Keyframe:
    """A key frame at the true pose T_true seeing the landmarks in view, placed
    (with its landmarks, from 'depth') at the estimated pose T_est."""
    p_C = xyz @ T_true[:3, :3].T + T_true[:3, 3]
    z = p_C[:, 2]
    uv = p_C[:, :2] / np.maximum(z, 1e-6)[:, None] * FX + [W / 2, H / 2]
    see = (z > 0.3) & (z < 6.0) & (uv[:, 0] > 0) & (uv[:, 0] < W) & (uv[:, 1] > 0) & (uv[:, 1] < H)
    p_C = p_C[see] + rng.normal(0.0, 0.002, (int(see.sum()), 3))
    T_wc = inverse(T_est)
    return Keyframe(kf_id, 0.1 * kf_id, T_est, np.zeros((1, 1), np.uint8), uv[see],
                    _noisy(desc[see], rng), p_C @ T_wc[:3, :3].T + T_wc[:3, 3], ids[see],
                    None, None, p_C[:, 2])


def _run(kfs: list[Keyframe], enabled: bool = True, min_gap: int = 20) -> LoopClosing:
    local = LocalMap(max_keyframes=10, local=5)  # forgets: the loop must be found again
    loops = LoopClosing(local, K, LoopSettings(min_gap=min_gap), enabled=enabled)
    for kf in kfs:
        local.add(kf)
        loops.on_keyframe(kf)
        while not loops.idle:
            loops.step()
    return loops


def _ate(T_cw: list[np.ndarray], truth: list[np.ndarray]) -> float:
    est = np.array([camera_in_world(T)[0] for T in T_cw])
    gt = np.array([camera_in_world(T)[0] for T in truth])
    R, t = umeyama_se3(est, gt)
    return float(np.sqrt(np.mean(np.sum((est @ R.T + t - gt) ** 2, axis=1))))


def test_a_drifted_loop_is_found_and_closed() -> None:
    """1.3 turns on a 1.5 m circle in a 8 m x 8 m room, looking outwards, the
    odometry turning 0.4 deg too far per key frame (~19 deg, ~0.5 m at the
    return). Landmarks seen again after the turn get new ids (the local map
    forgot them). Loop closing accepts a loop at the return, and the
    key-frame ATE drops to under half of the drifted one; switched off, it
    neither queries nor moves anything. Key frames are 0.1 s apart."""
    rng = np.random.default_rng(3)
    n_lm = 1500
    side = rng.integers(0, 4, n_lm)
    along = rng.uniform(-4.0, 4.0, n_lm)
    height = rng.uniform(-1.0, 1.5, n_lm)
    wall = np.where(side % 2 == 0, 4.0, -4.0)
    xyz = np.where((side < 2)[:, None], np.stack([wall, along, height], 1),
                   np.stack([along, wall, height], 1))
    desc = rng.integers(0, 256, (n_lm, 32), dtype=np.uint8)
    n_turn = 48
    truth, drifted_est = [], []
    local = LocalMap(max_keyframes=10, local=5)  # forgets: the loop must be found again
    loops = LoopClosing(local, K)
    kfs = []
    for k in range(int(1.3 * n_turn)):
        a = 2 * np.pi * k / n_turn
        T_true = _camera(np.array([1.5 * np.cos(a), 1.5 * np.sin(a), 0.0]), a)
        if k == 0:
            T_est = T_dr = T_true
        else:  # the true step, turned 0.4 deg too far, from the previous key frame as now known
            err = make_pose(Rotation.from_rotvec([0, np.radians(0.4), 0]).as_matrix(), np.zeros(3))
            step = err @ T_true @ inverse(truth[-1])  # T_ck_c(k-1), with the error
            T_est = step @ loops.pose_of(k - 1)
            T_dr = step @ drifted_est[-1]
        truth.append(T_true)
        drifted_est.append(T_dr)
        ids = np.arange(n_lm) + (10**6 if k >= n_turn else 0)
        kfs.append(_keyframe(k, T_true, T_est, xyz, desc, ids, rng))
        local.add(kfs[-1])
        loops.on_keyframe(kfs[-1])
        while not loops.idle:
            loops.step()
    drifted = _ate(drifted_est, truth)
    # one correction: the later loops (the odometry keeps drifting) wait as
    # edges, since corrections are resets for the autopilot (min_interval_s)
    assert loops.stats.accepted >= 2 and loops.stats.corrections == 1, loops.stats
    closed = _ate([loops.pose_of(k.keyframe_id) for k in kfs], truth)
    assert drifted > 0.1 and closed < 0.5 * drifted, (drifted, closed)
    off = _run(kfs, enabled=False)
    assert off.stats.queries == 0 and off.stats.corrections == 0


def test_a_repetitive_wall_gives_no_false_loop() -> None:
    """Flying 7 m along a wall whose texture repeats every 3 m (wider than
    the 2.6 m view at 2 m, so no key frame sees a pattern twice): a key
    frame matches the one a period back perfectly, geometry included, but
    the correction it asks for (3 m after 3 m flown, no drift at all) is
    beyond the drift bound: detected, never accepted."""
    rng = np.random.default_rng(5)
    n_pat = 150
    base_x = rng.uniform(0.0, 3.0, n_pat)
    base_z = rng.uniform(-1.0, 1.0, n_pat)
    base_desc = rng.integers(0, 256, (n_pat, 32), dtype=np.uint8)
    periods = 4
    xyz = np.concatenate([np.stack([base_x + 3.0 * n, np.full(n_pat, 2.0), base_z], 1)
                          for n in range(-1, periods)])
    desc = np.tile(base_desc, (periods + 1, 1))
    ids = np.arange(len(xyz))
    kfs = []
    for k in range(int(7.0 / 0.2)):
        T = _camera(np.array([0.2 * k, 0.0, 0.0]), np.pi / 2)
        kfs.append(_keyframe(k, T, T, xyz, desc, ids, rng))
    loops = _run(kfs, min_gap=10)
    assert loops.stats.detected > 0  # the repetition does fool recognition and RANSAC
    assert loops.stats.accepted == 0 and loops.stats.corrections == 0, loops.stats
    for kf in kfs[-10:]:  # nothing moved
        assert np.allclose(loops.pose_of(kf.keyframe_id), kf.T_cw)


def test_verify_recovers_the_relative_pose() -> None:
    """3-D RANSAC with 40 % outliers returns the relative pose within 1 cm / 0.2 deg."""
    rng = np.random.default_rng(1)
    p_j = rng.uniform([-1.5, -1.0, 1.0], [1.5, 1.0, 4.0], (300, 3))
    T_ij = make_pose(Rotation.from_rotvec([0.05, -0.3, 0.02]).as_matrix(), np.array([0.4, 0.0, -0.2]))
    p_i = p_j @ T_ij[:3, :3].T + T_ij[:3, 3] + rng.normal(0, 0.003, (300, 3))
    p_i[:120] = rng.uniform([-1.5, -1.0, 1.0], [1.5, 1.0, 4.0], (120, 3))
    desc = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    ids = np.arange(300)
    a = KeyRecord(0, np.eye(4), desc, p_i, ids, 0.0)
    b = KeyRecord(1, np.eye(4), _noisy(desc, rng), p_j, ids + 1000, 1.0)
    v = verify(a, b, PlaceSettings(), rng)
    assert v is not None and 170 <= v.inliers <= 185, v
    err = inverse(T_ij) @ v.T_ij
    assert np.linalg.norm(err[:3, 3]) < 0.01
    assert np.degrees(np.linalg.norm(Rotation.from_matrix(err[:3, :3]).as_rotvec())) < 0.2


def test_no_loop_closure_switch_reaches_the_tracker_parameters() -> None:
    """`--no-loop-closure` (replay, bench) sets [fastorb] loop_closure = false."""
    import argparse

    from onboard.app.cli_tracking import _overrides
    from onboard.app.config import load_config

    assert load_config(None).fastorb.loop_closure
    off = load_config(None, _overrides(argparse.Namespace(no_loop_closure=True)), "command line")
    assert not off.fastorb.loop_closure


def test_switched_off_it_keeps_only_each_key_frames_pose() -> None:
    """With loop closing off nothing but a key frame's pose is ever read
    (`pose_of`, after the local map forgot it), so its record holds no
    descriptors or points: memory that would grow with the flight (14 MB a
    minute of `nislam run` on a looping flight when the fused tracker kept
    them, docs/fusion.md). A forgotten key frame's pose is still told."""
    rng = np.random.default_rng(4)
    xyz = rng.uniform([-2.0, 2.0, -1.5], [2.0, 6.0, 1.5], (800, 3))  # ahead: along +y
    desc = rng.integers(0, 256, (800, 32), dtype=np.uint8)
    ids = np.arange(800)
    poses = [_camera(np.array([0.05 * k, 0.0, 0.0]), np.pi / 2) for k in range(30)]
    kfs = [_keyframe(k, T, T, xyz, desc, ids, rng) for k, T in enumerate(poses)]
    assert min(len(kf.ids) for kf in kfs) > 100  # each key frame sees landmarks
    for enabled in (True, False):
        loops = _run(kfs, enabled=enabled)
        held = sum(r.desc.nbytes + r.p_C.nbytes + r.ids.nbytes for r in loops._records)
        assert (held > 0) if enabled else (held == 0), (enabled, held)
        np.testing.assert_array_equal(loops.pose_of(0), poses[0])  # forgotten by the local map


def test_the_fused_tracker_runs_fastorb_without_its_loop_closing() -> None:
    """The filter closes its loops on NI-SLAM's key clones; FastORB's own
    corrections would move its world under it. Whatever [fastorb] says."""
    from onboard.app.config import load_config
    from onboard.core.camera import CameraIntrinsics
    from onboard.fusion.registry import make_tracker

    cfg = load_config(None)
    assert cfg.fastorb.loop_closure
    fused = make_tracker("fused", CameraIntrinsics(FX, FX, W / 2, H / 2, W, H), cfg)
    fastorb = fused.links[1].tracker
    assert fastorb.name == "fastorb" and not fastorb.p.loop_closure and not fastorb.loops.enabled
    alone = make_tracker("fastorb", CameraIntrinsics(FX, FX, W / 2, H / 2, W, H), cfg)
    assert alone.loops.enabled
