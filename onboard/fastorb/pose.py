"""Camera pose from 3-D landmarks and tracked 2-D points: PnP with RANSAC,
robust Gauss-Newton refinement on the inliers, and a first-order covariance.

The refinement is ORB-SLAM2's motion-only bundle adjustment for RGB-D (which
FastORB-SLAM keeps): a point with a depth reading in the current frame adds a
third residual, the disparity of a virtual stereo pair, bf / z with bf = the
baseline times fx (ORB-SLAM2's TUM settings: bf = 40 px, i.e. about 0.08 m at
fx = 517). Pixels alone hardly tell a small sideways shift from a small turn
on a narrow lens; the disparity pins the translation.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from onboard.core.se3 import pose_from_rvec, rvec_tvec, se3_exp
from onboard.fastorb.kernels import pose_normal_equations, pose_residual_norms
from onboard.fastorb.refine_kernels import gate_px, refine_pose_loop


@dataclass(frozen=True)
class PnpSettings:
    reprojection_px: float = 3.0  # RANSAC inlier threshold
    iterations: int = 100  # RANSAC cap (OpenCV stops earlier at `confidence`)
    confidence: float = 0.99
    refine_iterations: int = 4  # Gauss-Newton iterations on the inliers (at most)
    huber_px: float = 1.0  # robust refinement; 0: plain cv2.solvePnPRefineLM
    sigma_gate: float = 3.0  # final inliers within this many robust sigmas; 0: reprojection_px
    min_gate_px: float = 1.5  # ... but never tighter than this
    bf_px: float = 0.0  # virtual stereo baseline x fx for the depth residual; 0: pixels only


@dataclass(frozen=True)
class PnpResult:
    T_cw: np.ndarray  # (4, 4)
    inliers: np.ndarray  # (N,) bool over the input correspondences
    rms_px: float  # reprojection RMS over the inliers after refinement
    cov: np.ndarray  # (6, 6) covariance of a left perturbation (phi, rho): exp(xi^) T_cw


def solve_pnp(
    xyz_W: np.ndarray,
    uv: np.ndarray,
    K: np.ndarray,
    s: PnpSettings,
    min_inliers: int,
    depth_m: np.ndarray | None = None,
    prior: np.ndarray | None = None,
) -> PnpResult | None:
    """T_cw from correspondences; None when fewer than `min_inliers` agree.

    RANSAC on minimal-set AP3P hypotheses; the consensus set is then refined
    (robust Gauss-Newton; with huber_px = 0 and no depth term,
    cv2.solvePnPRefineLM) and gated again. `depth_m` (N,): the current frame's
    depth at `uv` (0: none), for the disparity residual. `prior`: a predicted
    T_cw (the motion model's); the refinement starts from it instead of
    RANSAC's pose when RANSAC's re-fit lost its consensus set (see `_start`).
    """
    if len(xyz_W) < max(min_inliers, 6):
        return None
    obj = np.ascontiguousarray(xyz_W, np.float64)
    img = np.ascontiguousarray(uv, np.float64)
    disp = disparity(depth_m, len(obj), s.bf_px)
    found = _start(_ransac(obj, img, K, s), prior, obj, img, K, s)
    if found is None or found[1].sum() < min_inliers:
        return None
    T, inl = found
    T = _refine(T, obj, img, disp, inl, K, s, s.refine_iterations)
    # Inliers again under the refined pose (RANSAC's set came from a sample
    # fit), within `sigma_gate` robust standard deviations of the residuals:
    # with sub-pixel tracks a 2-3 px outlier would still pass the RANSAC
    # threshold and pull the pose along its weakest direction.
    inl = _gated(T, obj, img, disp, inl, K, s)
    if s.sigma_gate > 0 and inl.sum() >= min_inliers:
        T = _refine(T, obj, img, disp, inl, K, s, 1)  # already close
        inl = _gated(T, obj, img, disp, inl, K, s)
    if inl.sum() < min_inliers:
        return None
    rms, cov = _covariance(T, obj, img, disp, inl, K, s)  # the final inliers only
    return PnpResult(T, inl, rms, cov)


def disparity(depth_m: np.ndarray | None, n: int, bf_px: float) -> np.ndarray:
    """Measured virtual-stereo disparity bf / z [px] per point, 0 without depth."""
    if depth_m is None or bf_px <= 0:
        return np.zeros(n)
    z = np.asarray(depth_m, np.float64)
    return np.where(z > 0, bf_px / np.where(z > 0, z, 1.0), 0.0)


def _ransac(
    obj: np.ndarray, img: np.ndarray, K: np.ndarray, s: PnpSettings
) -> tuple[np.ndarray, np.ndarray] | None:
    """(T_cw, inliers (N,) bool) of cv2.solvePnPRansac, or None.

    Minimal-set AP3P hypotheses (four points each; OpenCV refits the consensus
    set with EPnP): about 0.4 ms for 400 points, a quarter of iterative-PnP
    hypotheses started from the prior, and as good once refined. The motion
    prior enters in the refinement and the plausibility check instead.
    """
    ok, rvec, tvec, idx = cv2.solvePnPRansac(
        obj, img, K, None, iterationsCount=s.iterations,
        reprojectionError=s.reprojection_px, confidence=s.confidence,
        flags=cv2.SOLVEPNP_AP3P,
    )
    if not ok or idx is None:
        return None
    inl = np.zeros(len(obj), bool)
    inl[idx.ravel()] = True
    return pose_from_rvec(rvec, tvec), inl


def _start(
    found: tuple[np.ndarray, np.ndarray] | None, prior: np.ndarray | None, obj: np.ndarray,
    img: np.ndarray, K: np.ndarray, s: PnpSettings,
) -> tuple[np.ndarray, np.ndarray] | None:
    """(T_cw, inliers) to refine from: RANSAC's pose and consensus set,
    unless its re-fit pose agrees (within reprojection_px) with fewer than
    half of that set (a failed re-fit, not a point or two at the gate's edge)
    and the prior with more than the re-fit: then the prior and the points
    that agree with it. OpenCV's AP3P RANSAC re-fits its consensus set with EPnP, and
    that re-fit can land far off: on the synthetic `circle` flight (a
    column 1.2 m away filling the view) it returned a pose 1.3 m from the
    truth with a 12.7 px median error for a set RANSAC counted 498 of 530
    strong, and the Gauss-Newton refinement cannot come back from there
    (the track was lost twice, 2 resets). ORB-SLAM2 tracks from the motion
    model's pose and keeps PnP RANSAC for re-localisation; here both compete."""
    if prior is None:
        return found

    def agreeing(T: np.ndarray) -> np.ndarray:
        err = pose_residual_norms(np.ascontiguousarray(T[:3, :3]), T[:3, 3].copy(), obj, img,
                                  np.zeros(len(obj)), K[0, 0], K[1, 1], K[0, 2], K[1, 2], 0.0)
        return err <= s.reprojection_px

    if found is None:
        at_prior = agreeing(prior)
        return (prior, at_prior) if at_prior.any() else None
    n_fit = int(agreeing(found[0]).sum())
    if 2 * n_fit >= found[1].sum():
        return found  # the re-fit kept most of its consensus set: as without a prior
    at_prior = agreeing(prior)
    if n_fit >= at_prior.sum():
        return found
    return prior, at_prior  # the re-fit lost its set, and the prediction fits more


def _refine(
    T_cw: np.ndarray, obj: np.ndarray, img: np.ndarray, disp: np.ndarray, sel: np.ndarray,
    K: np.ndarray, s: PnpSettings, iterations: int,
) -> np.ndarray:
    """The pose refined on the points with `sel`."""
    if s.huber_px > 0 or s.bf_px > 0:
        return refine_pose(T_cw, obj, img, K, s.huber_px, iterations, disp, s.bf_px, sel)
    rvec, tvec = rvec_tvec(T_cw)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, 1e-10)
    rvec, tvec = cv2.solvePnPRefineLM(obj[sel], img[sel], K, None, rvec, tvec, criteria)
    return pose_from_rvec(rvec, tvec)


def _gated(
    T_cw: np.ndarray, obj: np.ndarray, img: np.ndarray, disp: np.ndarray, inl: np.ndarray,
    K: np.ndarray, s: PnpSettings,
) -> np.ndarray:
    """Points whose residual under T_cw is within the gate drawn from `inl`."""
    err = pose_residual_norms(np.ascontiguousarray(T_cw[:3, :3]), T_cw[:3, 3].copy(), obj, img,
                              disp, K[0, 0], K[1, 1], K[0, 2], K[1, 2], s.bf_px)
    return err <= gate_px(err, inl, float(s.sigma_gate), float(s.min_gate_px),
                          float(s.reprojection_px))  # _gate, compiled


def _gate(err_inliers: np.ndarray, s: PnpSettings) -> float:
    """Inlier threshold [px]: sigma_gate robust sigmas (the median 2-D error
    of a Gaussian is 1.177 sigma), between min_gate_px and reprojection_px.
    The floor matters on real data: points tracked for one frame from
    landmarks just made fit almost exactly, and a gate drawn from them alone
    would drop every older landmark, the ones that hold drift back."""
    if s.sigma_gate <= 0 or len(err_inliers) == 0:
        return s.reprojection_px
    sigma = float(np.median(err_inliers)) / 1.177
    return float(np.clip(s.sigma_gate * sigma, s.min_gate_px, s.reprojection_px))


def refine_pose(
    T_cw: np.ndarray, obj: np.ndarray, img: np.ndarray, K: np.ndarray, huber_px: float,
    iterations: int, disp: np.ndarray | None = None, bf_px: float = 0.0,
    sel: np.ndarray | None = None,
) -> np.ndarray:
    """Gauss-Newton on the reprojection error (plus the disparity residual
    where `disp` > 0) with Huber weights (a residual beyond `huber_px` counts
    linearly): points whose track has drifted by a pixel or two pull the pose
    far less than in plain least squares. Only the points with `sel` (all
    by default) count. The normal equations of `_residuals` come from one
    compiled pass (fastorb_kernels.pose_normal_equations), the iterations
    from one compiled loop (refine_kernels.refine_pose_loop)."""
    obj = np.ascontiguousarray(obj, np.float64)
    img = np.ascontiguousarray(img, np.float64)
    disp = np.zeros(len(obj)) if disp is None else np.ascontiguousarray(disp, np.float64)
    sel = np.ones(len(obj), bool) if sel is None else sel
    T = np.ascontiguousarray(T_cw, np.float64)
    try:  # the loop compiled (refine_kernels); stops at a 10 um / 10 urad step
        return refine_pose_loop(T, obj, img, disp, np.ascontiguousarray(sel, np.bool_), K[0, 0],
                                K[1, 1], K[0, 2], K[1, 2], float(bf_px), float(huber_px),
                                int(iterations))
    except np.linalg.LinAlgError:  # a zero pivot the pre-check missed: the loop in numpy
        return _refine_pose_numpy(T, obj, img, disp, sel, K, bf_px, huber_px, iterations)


def _refine_pose_numpy(
    T: np.ndarray, obj: np.ndarray, img: np.ndarray, disp: np.ndarray, sel: np.ndarray,
    K: np.ndarray, bf_px: float, huber_px: float, iterations: int,
) -> np.ndarray:
    """refine_pose's loop in numpy (the compiled loop's reference)."""
    for _ in range(iterations):
        H, g = _normal_equations(T, obj, img, disp, sel, K, bf_px, huber_px)[:2]
        try:
            step = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        T = se3_exp(step) @ T
        if float(np.abs(step).max()) < 1e-5:  # 10 um / 10 urad: converged
            break
    return T


def _normal_equations(
    T_cw: np.ndarray, obj: np.ndarray, img: np.ndarray, disp: np.ndarray, sel: np.ndarray,
    K: np.ndarray, bf_px: float, huber_px: float,
) -> tuple:
    return pose_normal_equations(np.ascontiguousarray(T_cw[:3, :3]), T_cw[:3, 3].copy(), obj,
                                 img, disp, sel, K[0, 0], K[1, 1], K[0, 2], K[1, 2], bf_px,
                                 huber_px)


def _residuals(
    T_cw: np.ndarray, obj: np.ndarray, img: np.ndarray, disp: np.ndarray, K: np.ndarray,
    bf_px: float, jacobian: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Residuals (N, 3) [px]: reprojection (u, v) and, where a disparity was
    measured (disp > 0), predicted minus measured disparity bf / z (0
    elsewhere); their Jacobians (N, 3, 6) with respect to a left perturbation
    (phi, rho) of T_cw: exp(xi^) T_cw, i.e. d(residual)/dp [-[p]x | I]
    (None with `jacobian` false: the inlier gates need the residuals only)."""
    p = obj @ T_cw[:3, :3].T + T_cw[:3, 3]
    iz = 1.0 / np.maximum(p[:, 2], 1e-6)
    xz, yz = p[:, 0] * iz, p[:, 1] * iz
    fx, fy = K[0, 0], K[1, 1]
    res = np.zeros((len(p), 3))
    res[:, 0] = fx * xz + K[0, 2] - img[:, 0]
    res[:, 1] = fy * yz + K[1, 2] - img[:, 1]
    has = disp > 0
    if not jacobian:
        if bf_px > 0:
            res[has, 2] = bf_px * iz[has] - disp[has]
        return res, None
    J = np.zeros((len(p), 3, 6))
    J[:, 0, 0] = -fx * xz * yz
    J[:, 0, 1] = fx * (1.0 + xz * xz)
    J[:, 0, 2] = -fx * yz
    J[:, 0, 3] = fx * iz
    J[:, 0, 5] = -fx * xz * iz
    J[:, 1, 0] = -fy * (1.0 + yz * yz)
    J[:, 1, 1] = fy * xz * yz
    J[:, 1, 2] = fy * xz
    J[:, 1, 4] = fy * iz
    J[:, 1, 5] = -fy * yz * iz
    if bf_px > 0 and has.any():
        # d(bf/z)/dp = -bf/z^2 e_z; e_z^T [-[p]x | I] = [y, -x, 0, 0, 0, 1]
        res[has, 2] = bf_px * iz[has] - disp[has]
        g = -bf_px * iz[has] ** 2
        J[has, 2, 0] = g * p[has, 1]
        J[has, 2, 1] = -g * p[has, 0]
        J[has, 2, 5] = g
    return res, J


def _covariance(
    T_cw: np.ndarray, obj: np.ndarray, img: np.ndarray, disp: np.ndarray, sel: np.ndarray,
    K: np.ndarray, s: PnpSettings,
) -> tuple[float, np.ndarray]:
    """Reprojection RMS over the points with `sel` and sigma^2 (J^T W J)^-1
    of the left perturbation (phi, rho), sigma^2 the weighted residual
    variance with 6 degrees of freedom taken out (floored at (0.1 px)^2,
    quantisation noise); a point without a disparity residual adds 2
    observations, one with it 3."""
    H, _g, sse_w, sse_px, n_obs, n = _normal_equations(T_cw, obj, img, disp, sel, K, s.bf_px,
                                                        s.huber_px)
    sigma2 = max(sse_w / max(n_obs - 6, 1), 0.01)
    try:
        cov = sigma2 * np.linalg.inv(H)
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.nan)
    return float(np.sqrt(sse_px / max(n, 1))), cov


def world_pose_variance(T_cw: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(6,) variances of the camera position p_W (x, y, z, m^2) and of small
    rotations about the world axes x, y, z (rad^2), from the covariance of the
    left perturbation (phi, rho) of T_cw. To first order p_W = -R^T t moves by
    -R^T rho and R_W_C turns by -R^T phi in world axes."""
    Rt = T_cw[:3, :3].T
    var_p = np.diag(Rt @ cov[3:, 3:] @ Rt.T)
    var_r = np.diag(Rt @ cov[:3, :3] @ Rt.T)
    var = np.concatenate([var_p, var_r])
    return np.where(np.isfinite(var), np.maximum(var, 0.0), np.nan)


def landmark_sd(T_cw: np.ndarray, cov: np.ndarray, xyz_W: np.ndarray) -> float:
    """The error [m, 1 sd] a pose with covariance `cov` (left perturbation
    (phi, rho) of T_cw) puts into landmarks placed from it at the points
    `xyz_W`: the median over the points of the largest per-axis sd. A point
    p_C back-projected from its pixel and depth lands at R^T (p_C - t); under
    exp(xi^) T_cw it moves by -R^T [-[p_C]x | I] xi (to first order), so its
    covariance is J cov J^T with J = [-[p_C]x | I] (camera axes; R^T keeps
    the spread). A point at the camera centre gives the position's own sd.
    NaN without points or with a non-finite covariance."""
    if len(xyz_W) == 0 or not np.all(np.isfinite(cov)):
        return float("nan")
    p = xyz_W @ T_cw[:3, :3].T + T_cw[:3, 3]
    J = np.zeros((len(p), 3, 6))
    J[:, :, 3:] = np.eye(3)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    J[:, 0, 1], J[:, 0, 2] = z, -y  # -[p]x
    J[:, 1, 0], J[:, 1, 2] = -z, x
    J[:, 2, 0], J[:, 2, 1] = y, -x
    var = np.einsum("nij,jk,nik->ni", J, cov, J)
    return float(np.sqrt(np.median(np.maximum(var, 0.0).max(axis=1))))


def restricted(pnp: PnpResult) -> PnpResult:
    """The PnP result over its own inliers only (the tracked set keeps those)."""
    return PnpResult(pnp.T_cw, np.ones(int(pnp.inliers.sum()), bool), pnp.rms_px, pnp.cov)
