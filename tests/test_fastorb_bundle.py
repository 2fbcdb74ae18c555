"""Local bundle adjustment on GTSAM (onboard/fastorb/bundle.py): a synthetic
problem with known truth, perturbed, converges back to it."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from onboard.core.se3 import inverse, make_pose, se3_exp
from onboard.fastorb.bundle import BaProblem, BaSettings, LocalBundle

K = np.array([[525.0, 0.0, 320.0], [0.0, 525.0, 240.0], [0.0, 0.0, 1.0]])


def _problem(seed: int = 0):
    """Six key frames 0.1 m apart looking down +z with small turns, 400
    points 1.5-5 m ahead; every key frame sees the points in its image; points seen
    by fewer than three are left out.
    Returns the truth and the observations (exact pixels and depths)."""
    rng = np.random.default_rng(seed)
    T_cw = []
    for i in range(6):
        R_W_C = Rotation.from_euler("xyz", [2 * np.sin(i), 3 * np.cos(i), i], degrees=True)
        T_cw.append(inverse(make_pose(R_W_C.as_matrix(), np.array([0.1 * i, 0.02 * i, 0.0]))))
    T_cw = np.array(T_cw)
    xyz = rng.uniform([-2.0, -1.5, 1.5], [2.5, 1.5, 5.0], (400, 3))
    kf, lm, uv, z = [], [], [], []
    for i, T in enumerate(T_cw):
        pc = xyz @ T[:3, :3].T + T[:3, 3]
        u = K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]
        v = K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]
        seen = np.flatnonzero((u >= 0) & (u < 640) & (v >= 0) & (v < 480))
        kf.append(np.full(len(seen), i))
        lm.append(seen)
        uv.append(np.stack([u[seen], v[seen]], axis=1))
        z.append(pc[seen, 2])
    kf, lm, uv, z = (np.concatenate(a) for a in (kf, lm, uv, z))
    views = np.bincount(lm, minlength=len(xyz))
    keep = np.flatnonzero(views >= 3)  # as local mapping's culling keeps them
    new_index = np.full(len(xyz), -1)
    new_index[keep] = np.arange(len(keep))
    o = views[lm] >= 3
    return T_cw, xyz[keep], (kf[o], new_index[lm[o]], uv[o], z[o])


def test_local_ba_converges_to_the_truth() -> None:
    """Two anchor key frames fixed, the other four moved by ~2 cm / 1 deg and
    every point by ~2 cm, 2 % of the observations grossly wrong (20-40 px):
    poses and points come back within 1 mm of the truth (measured: ~1e-14 m),
    and the wrong observations, only they, are flagged (dropped before the
    second stage). Points beyond 3 m
    enter as plain projections, nearer ones as stereo measurements."""
    T_true, xyz_true, (kf, lm, uv, z) = _problem()
    rng = np.random.default_rng(1)
    bad = rng.choice(len(kf), len(kf) // 50, replace=False)
    uv = uv.copy()
    uv[bad] += rng.choice([-1, 1], (len(bad), 2)) * rng.uniform(20, 40, (len(bad), 2))
    fixed = np.array([True, True, False, False, False, False])
    T0 = T_true.copy()
    for i in np.flatnonzero(~fixed):
        T0[i] = se3_exp(np.r_[rng.normal(0, 0.015, 3), rng.normal(0, 0.02, 3)]) @ T_true[i]
    xyz0 = xyz_true + rng.normal(0, 0.02, xyz_true.shape)
    problem = BaProblem(np.arange(6), T0, fixed, np.arange(len(xyz0)), xyz0, kf, lm, uv, z)
    assert ((z > 0) & (z < 3.0)).any() and (z >= 3.0).any()  # both kinds of factor
    res = LocalBundle(problem, K, BaSettings(bf_px=40.0, max_depth_m=3.0,
                                             max_iterations=30)).run()
    pos_err = [np.linalg.norm(inverse(res.T_cw[i])[:3, 3] - inverse(T_true[i])[:3, 3])
               for i in range(6)]
    rot_err = [np.linalg.norm(Rotation.from_matrix(res.T_cw[i][:3, :3] @ T_true[i][:3, :3].T)
                              .as_rotvec()) for i in range(6)]
    print("pose errors [m]:", np.max(pos_err), "points:", np.abs(res.xyz_W - xyz_true).max())
    assert max(pos_err) < 1e-3 and max(rot_err) < 1e-4
    assert np.array_equal(res.T_cw[:2], T0[:2])  # the anchors stay
    assert np.linalg.norm(res.xyz_W - xyz_true, axis=1).max() < 1e-3
    flagged = np.flatnonzero(res.outliers)
    assert set(flagged) == set(bad)


def test_local_ba_in_steps_and_nothing_to_do() -> None:
    """Stepped one LM iteration at a time it ends on its own (converged or
    max_iterations); with every key frame fixed it is done at once."""
    T_true, xyz_true, (kf, lm, uv, z) = _problem(2)
    fixed = np.array([True] + [False] * 5)
    T0 = T_true.copy()
    T0[3] = se3_exp(np.r_[0.0, 0.01, 0.0, 0.02, 0.0, 0.0]) @ T_true[3]
    problem = BaProblem(np.arange(6), T0, fixed, np.arange(len(xyz_true)), xyz_true.copy(),
                        kf, lm, uv, z)
    ba = LocalBundle(problem, K, BaSettings(max_iterations=8))
    steps = 0
    while not ba.step():
        steps += 1
        assert steps < 8
    assert np.linalg.norm(inverse(ba.result().T_cw[3])[:3, 3] - inverse(T_true[3])[:3, 3]) < 1e-3
    problem.fixed[:] = True
    assert LocalBundle(problem, K).done


def test_stereo_noise_model_and_estimated_sigmas() -> None:
    """Pixels with a 0.2 px sd and disparities with a 0.8 px sd: the BA's
    second stage estimates both within 25 % (estimate_sigmas), and the
    stereo factor's covariance keeps them apart (the old isotropic 1 px on
    (u_L, u_R, v) could not tell them)."""
    T_true, xyz_true, (kf, lm, uv, z) = _problem(3)
    rng = np.random.default_rng(4)
    bf = 400.0
    uv = uv + rng.normal(0, 0.2, uv.shape)
    z = bf / (bf / z + rng.normal(0, 0.8, z.shape))
    fixed = np.array([True, True, False, False, False, False])
    problem = BaProblem(np.arange(6), T_true.copy(), fixed, np.arange(len(xyz_true)),
                        xyz_true.copy(), kf, lm, uv, z)
    ba = LocalBundle(problem, K, BaSettings(bf_px=bf, max_depth_m=10.0, estimate_sigmas=True))
    ba.run()
    print("estimated sds:", ba.pixel_sigma, ba.disparity_sigma)
    assert abs(ba.pixel_sigma - 0.2) < 0.05 and abs(ba.disparity_sigma - 0.8) < 0.2
