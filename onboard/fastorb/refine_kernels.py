"""Compiled Gauss-Newton loops of FastORB's pose refinement (numba), beside
kernels.py: per iteration the Python loops paid more for their calls
(np.linalg.solve, the SE(3) exponential through cv2.Rodrigues, a dozen
(N, 3, 9) temporaries for the rolling-shutter fit) than for the arithmetic
on a few hundred points. Here one call runs every iteration.

  refine_pose_loop   pose.refine_pose: robust GN on reprojection + disparity
  refine_rate_loop   shutter.refine_with_rate: pose and body rate from the
                     rows' shear (9 unknowns, rate prior)
  gate_px            pose._gate: the inlier threshold from a median

The same equations as the numpy forms (the tests compare them on random
problems). refine_pose_loop gives numpy's bits (the same kernels, LAPACK and
BLAS calls and formula order); the rate fit sums its 9 x 9 system in
another order than numpy's BLAS product and agrees to rounding (~1e-15
relative). `warm_up()` compiles them with the other kernels.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from onboard.fastorb.kernels import pose_normal_equations


@njit(cache=True, nogil=True)
def se3_exp_left(xi, T):
    """exp(xi^) T for a twist xi = (phi, rho) and a 4x4 T, bit for bit as
    core.se3.se3_exp(xi) @ T computes it: cv2.Rodrigues's formula in its
    order of operations, the left Jacobian V as se3._v_matrix writes it
    (Python's a**n is C pow), and the products through BLAS as numpy's
    matmul (tests/test_fastorb_speed.py checks the bits)."""
    phi = xi[:3].copy()
    rho = xi[3:6].copy()
    p0, p1, p2 = phi[0], phi[1], phi[2]
    R = np.eye(3)
    theta = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
    if theta >= 2.220446049250313e-16:  # cv2.Rodrigues: the identity below DBL_EPSILON
        c = math.cos(theta)
        s = math.sin(theta)
        c1 = 1.0 - c
        it = 1.0 / theta
        r0, r1, r2 = p0 * it, p1 * it, p2 * it
        R[0, 0] = c + c1 * (r0 * r0)
        R[0, 1] = c1 * (r0 * r1) + s * (-r2)
        R[0, 2] = c1 * (r0 * r2) + s * r1
        R[1, 0] = c1 * (r0 * r1) + s * r2
        R[1, 1] = c + c1 * (r1 * r1)
        R[1, 2] = c1 * (r1 * r2) + s * (-r0)
        R[2, 0] = c1 * (r0 * r2) + s * (-r1)
        R[2, 1] = c1 * (r1 * r2) + s * r0
        R[2, 2] = c + c1 * (r2 * r2)
    a = math.sqrt(np.dot(phi, phi))
    K = np.zeros((3, 3))
    K[0, 1], K[0, 2], K[1, 0], K[1, 2], K[2, 0], K[2, 1] = -p2, p1, p2, -p0, -p1, p0
    KK = K @ K
    if a < 1e-6:
        V = np.eye(3) + 0.5 * K + KK / 6.0
    else:
        # C pow as Python's a**2 calls it; a literal 2.0 would let LLVM
        # write a * a, which pow rounds otherwise in ~1 case in 1000.
        two = 2.0 + 0.0 * a
        V = (np.eye(3) + (1.0 - math.cos(a)) / math.pow(a, two) * K
             + (a - math.sin(a)) / math.pow(a, 3.0) * KK)
    E = np.eye(4)
    E[:3, :3] = R
    E[:3, 3] = V @ rho
    return E @ np.ascontiguousarray(T)


@njit(cache=True, nogil=True)
def refine_pose_loop(T, obj, img, disp, sel, fx, fy, cx, cy, bf, huber, iterations):
    """pose.refine_pose: up to `iterations` Huber Gauss-Newton steps on the
    points with `sel`, stopping at a step under 1e-5 or a singular system."""
    for _ in range(iterations):
        R = np.ascontiguousarray(T[:3, :3])
        t = T[:3, 3].copy()
        H, g, _sw, _sp, _no, _n = pose_normal_equations(R, t, obj, img, disp, sel, fx, fy, cx,
                                                        cy, bf, huber)
        if not _solvable(H):
            break
        step = -np.linalg.solve(H, g)
        T = se3_exp_left(step, T)
        if np.abs(step).max() < 1e-5:
            break
    return T


@njit(cache=True, nogil=True)
def _solvable(H):
    """Whether LU with partial pivoting gets through H without a zero pivot
    (np.linalg.solve's LinAlgError), without raising inside compiled code."""
    A = H.copy()
    n = A.shape[0]
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(A[i, k]) > abs(A[p, k]):
                p = i
        if A[p, k] == 0.0:
            return False
        if p != k:
            for j in range(n):
                A[k, j], A[p, j] = A[p, j], A[k, j]
        for i in range(k + 1, n):
            f = A[i, k] / A[k, k]
            for j in range(k, n):
                A[i, j] -= f * A[k, j]
    return True


@njit(cache=True, nogil=True)
def rate_normal_equations(T, omega, rho, obj, uv, disp, tau, fx, fy, cx, cy, bf, huber):
    """The 9 x 9 Gauss-Newton system of shutter.refine_with_rate (without
    the rate prior): pose (phi, rho) and body rate omega, each point's
    residual (u, v, disparity) at q = p + tau (omega x p + rho), Huber
    weights on the residual norm."""
    H = np.zeros((9, 9))
    g = np.zeros(9)
    J = np.zeros((3, 9))
    r = np.zeros(3)
    wx, wy, wz = omega[0], omega[1], omega[2]
    for i in range(len(obj)):
        X = obj[i]
        x = T[0, 0] * X[0] + T[0, 1] * X[1] + T[0, 2] * X[2] + T[0, 3]
        y = T[1, 0] * X[0] + T[1, 1] * X[1] + T[1, 2] * X[2] + T[1, 3]
        z = T[2, 0] * X[0] + T[2, 1] * X[1] + T[2, 2] * X[2] + T[2, 3]
        ti = tau[i]
        qx = x + ti * ((wy * z - wz * y) + rho[0])
        qy = y + ti * ((wz * x - wx * z) + rho[1])
        qz = z + ti * ((wx * y - wy * x) + rho[2])
        iz = 1.0 / max(qz, 1e-6)
        has = disp[i] > 0 and bf > 0
        r[0] = fx * qx * iz + cx - uv[i, 0]
        r[1] = fy * qy * iz + cy - uv[i, 1]
        r[2] = bf * iz - disp[i] if has else 0.0
        iz2 = iz * iz
        a = fx * iz
        b = -fx * qx * iz2
        c = fy * iz
        e = -fy * qy * iz2
        dd = -bf * iz2 if has else 0.0
        J[0, 0], J[0, 1], J[0, 2] = b * y, a * z - b * x, -a * y
        J[1, 0], J[1, 1], J[1, 2] = -c * z + e * y, -e * x, c * x
        J[2, 0], J[2, 1], J[2, 2] = dd * y, -dd * x, 0.0
        J[0, 3], J[0, 4], J[0, 5] = a, 0.0, b
        J[1, 3], J[1, 4], J[1, 5] = 0.0, c, e
        J[2, 3], J[2, 4], J[2, 5] = 0.0, 0.0, dd
        for k in range(3):
            for m in range(3):
                J[k, 6 + m] = ti * J[k, m]
        norm = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
        w = 1.0 if norm <= huber else huber / max(norm, 1e-12)
        for m in range(9):
            acc = 0.0
            for k in range(3):
                acc += J[k, m] * r[k]
            g[m] += w * acc
            for n in range(m, 9):
                acc = 0.0
                for k in range(3):
                    acc += J[k, m] * J[k, n]
                H[m, n] += w * acc
    for m in range(9):
        for n in range(m):
            H[m, n] = H[n, m]
    return H, g


@njit(cache=True, nogil=True)
def refine_rate_loop(T, omega, rho, omega_prior, obj, uv, disp, tau, fx, fy, cx, cy, bf, huber,
                     rate_sd, iterations):
    """shutter.refine_with_rate's iterations: (T_cw, omega)."""
    omega = omega.copy()
    var = rate_sd * rate_sd
    for _ in range(iterations):
        H, g = rate_normal_equations(T, omega, rho, obj, uv, disp, tau, fx, fy, cx, cy, bf, huber)
        for m in range(3):
            H[6 + m, 6 + m] += 1.0 / var
            g[6 + m] += (omega[m] - omega_prior[m]) / var
        if not _solvable(H):
            break
        step = -np.linalg.solve(H, g)
        T = se3_exp_left(step[:6].copy(), T)
        omega = omega + step[6:]
        if np.abs(step).max() < 1e-6:
            break
    return T, omega


@njit(cache=True, nogil=True)
def gate_px(err, inl, sigma_gate, min_gate_px, max_gate_px):
    """pose._gate over err[inl]: sigma_gate x median / 1.177 within
    [min_gate_px, max_gate_px]; max_gate_px without inliers."""
    sub = err[inl]
    if sigma_gate <= 0 or len(sub) == 0:
        return max_gate_px
    sigma = np.median(sub) / 1.177
    return min(max(sigma_gate * sigma, min_gate_px), max_gate_px)


def warm_up() -> None:
    """Compile (or load) the loops for the tracker's argument types."""
    T = np.eye(4)
    obj = np.array([[0.1, 0.2, 2.0], [-0.3, 0.1, 1.5], [0.2, -0.2, 3.0], [0.0, 0.0, 2.5]])
    img = np.array([[330.0, 250.0], [300.0, 260.0], [340.0, 230.0], [320.0, 240.0]])
    disp = np.array([20.0, 0.0, 13.0, 16.0])
    sel = np.ones(4, np.bool_)
    refine_pose_loop(T, obj, img, disp, sel, 500.0, 500.0, 320.0, 240.0, 40.0, 1.0, 1)
    v3 = np.zeros(3)
    refine_rate_loop(T, v3, v3, v3, obj, img, disp, np.zeros(4), 500.0, 500.0, 320.0, 240.0,
                     40.0, 1.0, 0.5, 1)
    gate_px(disp, sel, 3.0, 1.5, 3.0)
