"""Local bundle adjustment for FastORB's key frames on GTSAM (issue 18, item 1).

ORB-SLAM2's local BA for RGB-D (Mur-Artal and Tardos 2017, Sec. V-B; FastORB-
SLAM keeps it, Fu et al. Sec. III "Local mapping"): the poses of the new key
frame and its covisible key frames and the landmarks they see are refined
together; the other key frames that see those landmarks stay fixed and only
anchor the solution. A landmark observed with a depth reading closer than
max_depth_m is a stereo-like measurement (u_L, u_R, v), u_R = u_L - bf / z,
the virtual right camera of ORB-SLAM2's RGB-D mode, which pins the depth the
reprojection alone hardly sees; farther or without depth it is a plain
projection. Both robust (Huber at ORB-SLAM2's chi-square 95 % thresholds:
sqrt(7.815) for three residuals, sqrt(5.991) for two).

GTSAM does the work: `GenericStereoFactor3D` / `GenericProjectionFactorCal3_S2`
with `noiseModel.Robust(Huber)`, `NonlinearEqualityPose3` for the fixed key
frames, Levenberg-Marquardt. The optimiser is stepped one iteration at a time
(`LocalBundle.step`), so the caller can spread it over the idle time between
frames: GTSAM's Python binding holds the GIL while it works (measured: a main
thread got 3 turns of its loop during a 1.1 s optimisation in a second
thread), so a worker thread would stall tracking just the same.

Poses here are T_cw (world -> camera) as elsewhere in FastORB; GTSAM's Pose3
of a camera is T_wc.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from onboard.core.se3 import inverse

CHI2_STEREO = 7.815  # chi-square 95 %, 3 dof (ORB-SLAM2)
CHI2_MONO = 5.991  # ... 2 dof


@dataclass(frozen=True)
class BaSettings:
    bf_px: float = 120.0  # virtual stereo baseline x fx [px] (FastOrbParams.rgbd_bf_px)
    max_depth_m: float = 3.0  # depth used as a stereo measurement below this
    pixel_sigma: float = 1.0  # sd of a keypoint's pixel [px]
    disparity_sigma: float = 1.0  # sd of the virtual disparity bf / z [px]
    # True: the second stage weighs by the sds the first one's residuals show
    # (off: tum_fr1_rpy 0.051 m with it, 0.029 m without; docs/fastorb_backend.md)
    estimate_sigmas: bool = False
    min_sigma: float = 0.05  # ... but not below this [px]
    max_iterations: int = 10
    relative_tol: float = 1e-5  # stop when the error falls by less than this share


@dataclass
class BaProblem:
    """Key frames (P), landmarks (M) and observations (N) of one local BA."""

    kf_ids: np.ndarray  # (P,) key frame ids
    T_cw: np.ndarray  # (P, 4, 4)
    fixed: np.ndarray  # (P,) bool: anchors, not optimised
    lm_ids: np.ndarray  # (M,) landmark ids
    xyz_W: np.ndarray  # (M, 3)
    obs_kf: np.ndarray  # (N,) index into the key frames
    obs_lm: np.ndarray  # (N,) index into the landmarks
    obs_uv: np.ndarray  # (N, 2) pixel
    obs_z: np.ndarray  # (N,) measured depth [m], 0: none


@dataclass(frozen=True)
class BaResult:
    T_cw: np.ndarray  # (P, 4, 4), fixed ones unchanged
    xyz_W: np.ndarray  # (M, 3)
    outliers: np.ndarray  # (N,) bool: beyond the chi-square gate or behind the camera
    iterations: int  # of the last stage
    error_before: float
    error_after: float


class LocalBundle:
    """One local BA, built once and run by `step()` (one LM iteration each)
    until `done`; then `result()`."""

    def __init__(self, problem: BaProblem, K: np.ndarray, s: BaSettings = BaSettings()):
        self.problem = problem
        self.s = s
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        self._mono_cal = gtsam.Cal3_S2(fx, fy, 0.0, cx, cy)
        self._stereo_cal = gtsam.Cal3_S2Stereo(fx, fy, 0.0, cx, cy, s.bf_px / fx)
        self._stereo = self._stereo_obs()
        self._kept = np.ones(len(problem.obs_kf), bool)  # observations in the graph
        self._stage = 1
        self.pixel_sigma, self.disparity_sigma = s.pixel_sigma, s.disparity_sigma
        self._opt = self._optimizer(self._initial_values())
        self.error_before = float(self._opt.error())
        self._last_error = self.error_before
        self.done = len(problem.obs_kf) == 0 or bool(np.all(problem.fixed))

    def _initial_values(self) -> gtsam.Values:
        p = self.problem
        values = gtsam.Values()
        for i in range(len(p.kf_ids)):
            values.insert(X(i), gtsam.Pose3(inverse(p.T_cw[i])))
        for j in range(len(p.lm_ids)):
            values.insert(L(j), np.asarray(p.xyz_W[j], np.float64))
        return values

    def _optimizer(self, values: gtsam.Values) -> gtsam.LevenbergMarquardtOptimizer:
        """LM over the observations still kept, from `values`."""
        p, s = self.problem, self.s
        graph = gtsam.NonlinearFactorGraph()
        for i in np.flatnonzero(p.fixed):
            graph.add(gtsam.NonlinearEqualityPose3(X(int(i)), values.atPose3(X(int(i)))))
        huber = gtsam.noiseModel.mEstimator.Huber
        # (u_L, u_R, v) with u_R = u_L - d: u_R carries the pixel's error
        # and the disparity's, so the two u rows are correlated.
        sp2, sd2 = self.pixel_sigma**2, self.disparity_sigma**2
        stereo_noise = gtsam.noiseModel.Robust.Create(
            huber.Create(float(np.sqrt(CHI2_STEREO))),
            gtsam.noiseModel.Gaussian.Covariance(
                np.array([[sp2, sp2, 0.0], [sp2, sp2 + sd2, 0.0], [0.0, 0.0, sp2]])))
        mono_noise = gtsam.noiseModel.Robust.Create(
            huber.Create(float(np.sqrt(CHI2_MONO))),
            gtsam.noiseModel.Isotropic.Sigma(2, self.pixel_sigma))
        for n in np.flatnonzero(self._kept):
            u, v = float(p.obs_uv[n, 0]), float(p.obs_uv[n, 1])
            xk, lk = X(int(p.obs_kf[n])), L(int(p.obs_lm[n]))
            if self._stereo[n]:
                meas = gtsam.StereoPoint2(u, u - s.bf_px / float(p.obs_z[n]), v)
                graph.add(gtsam.GenericStereoFactor3D(meas, stereo_noise, xk, lk,
                                                      self._stereo_cal))
            else:
                graph.add(gtsam.GenericProjectionFactorCal3_S2(
                    np.array([u, v]), mono_noise, xk, lk, self._mono_cal))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(s.max_iterations)
        return gtsam.LevenbergMarquardtOptimizer(graph, values, params)

    def _stereo_obs(self) -> np.ndarray:
        z = self.problem.obs_z
        return (z > 0) & (z < self.s.max_depth_m) if self.s.bf_px > 0 else np.zeros(len(z), bool)

    def step(self) -> bool:
        """One Levenberg-Marquardt iteration; True once finished. As ORB-SLAM2:
        a first stage runs to convergence (or max_iterations), the
        observations then beyond the chi-square gate are dropped, and a
        second stage starts from there without them (if any were dropped)."""
        if self.done:
            return True
        try:
            self._opt.iterate()
        except RuntimeError:  # an indeterminate system: keep what we have
            self.done = True
            return True
        err = float(self._opt.error())
        gain = self._last_error - err
        self._last_error = err
        if (self._opt.iterations() < self.s.max_iterations
                and gain > self.s.relative_tol * max(err, 1e-12)):
            return False
        if self._stage == 1:
            T, xyz = self._estimate()
            resized = self.s.estimate_sigmas and self._estimate_sigmas(T, xyz)
            out = self._outliers(T, xyz)
            if (out & self._kept).any() or resized:
                self._kept &= ~out
                self._stage = 2
                self._opt = self._optimizer(self._opt.values())
                self._last_error = float(self._opt.error())
                return False
        self.done = True
        return True

    def run(self) -> BaResult:
        """All the steps at once (tests, offline use)."""
        while not self.step():
            pass
        return self.result()

    def _estimate(self) -> tuple[np.ndarray, np.ndarray]:
        p = self.problem
        values = self._opt.values()
        T = p.T_cw.copy()
        for i in np.flatnonzero(~p.fixed):
            T[i] = inverse(values.atPose3(X(int(i))).matrix())
        xyz = np.array([values.atPoint3(L(j)) for j in range(len(p.lm_ids))]).reshape(-1, 3)
        return T, xyz

    def result(self) -> BaResult:
        T, xyz = self._estimate()
        return BaResult(T, xyz, self._outliers(T, xyz), int(self._opt.iterations()),
                        self.error_before, float(self._opt.error()))

    def _estimate_sigmas(self, T: np.ndarray, xyz: np.ndarray) -> bool:
        """The pixel and disparity sds the residuals of the kept observations
        show (1.4826 MAD, robust to the outliers still in, times
        sqrt(n / (n - parameters)) for what the fit absorbed). Why: ORB-SLAM2's
        fixed 1 px (octave 0) against a disparity sd of 1 px let the depth
        (2.4-3.6 cm sd at 4-5 m) outweigh sub-pixel tracks (0.2 px on the
        synthetic flights), and the key frames moved with the depth noise.
        Blurred recorded frames show larger sds and get them. False when
        there is too little to tell."""
        p = self.problem
        k = self._kept
        e_uv, e_d = self._residuals(T, xyz)
        e_uv, e_d = e_uv[k], e_d[k & self._stereo]
        n = e_uv.size + e_d.size
        params = 3 * len(p.lm_ids) + 6 * int((~p.fixed).sum())
        if e_uv.size < 20 or n <= 2 * params:
            return False
        c = 1.4826 * np.sqrt(n / (n - params))
        self.pixel_sigma = max(c * float(np.median(np.abs(e_uv))), self.s.min_sigma)
        if e_d.size >= 20:
            self.disparity_sigma = max(c * float(np.median(np.abs(e_d))), self.s.min_sigma)
        return True

    def _residuals(self, T: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel residuals (N, 2) and disparity residuals (N,), 0 without a
        stereo measurement or behind the camera."""
        p = self.problem
        Tk = T[p.obs_kf]
        pc = np.einsum("nij,nj->ni", Tk[:, :3, :3], xyz[p.obs_lm]) + Tk[:, :3, 3]
        zs = np.where(pc[:, 2] > 1e-6, pc[:, 2], 1.0)
        fx, fy = self._mono_cal.fx(), self._mono_cal.fy()
        e_uv = np.stack([fx * pc[:, 0] / zs + self._mono_cal.px() - p.obs_uv[:, 0],
                         fy * pc[:, 1] / zs + self._mono_cal.py() - p.obs_uv[:, 1]], axis=1)
        st = self._stereo
        e_d = np.where(st, self.s.bf_px / zs - self.s.bf_px / np.where(st, p.obs_z, 1.0), 0.0)
        return e_uv, e_d

    def _outliers(self, T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
        """ORB-SLAM2's gate after local BA: chi-square of an observation over
        7.815 (stereo) / 5.991 (mono), or a point behind the camera."""
        p = self.problem
        if len(p.obs_kf) == 0:
            return np.zeros(0, bool)
        Tk = T[p.obs_kf]
        z = np.einsum("nj,nj->n", Tk[:, 2, :3], xyz[p.obs_lm]) + Tk[:, 2, 3]
        e_uv, e_d = self._residuals(T, xyz)
        # In the configured sds (or the estimated ones if larger): an estimate
        # from nearly exact residuals would gate the slightest pull as an outlier.
        sp, sd = (max(self.pixel_sigma, self.s.pixel_sigma),
                  max(self.disparity_sigma, self.s.disparity_sigma))
        chi2 = np.sum(e_uv**2, axis=1) / sp**2 + e_d**2 / sd**2
        return (z <= 1e-6) | (chi2 > np.where(self._stereo, CHI2_STEREO, CHI2_MONO))
