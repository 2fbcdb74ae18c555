"""FastORB's new landmarks on a rolling-shutter camera, settled one frame
later with the body rate of the poses on both sides of the frame that made
them.

A landmark made from a pixel in row v and its depth is brought to the
middle row's instant with the body rate omega (shutter.points_at_mid:
p_mid = p_v - tau_v (omega x p_v + rho)). When the landmark is made, the
only rate at hand is the one the frame's own rows' shear measured
(shutter.refine_with_rate, its prior the last frame's): on tum_fr1_rpy it is
off from the ground truth's by 0.9-1.3 rad/s RMS per axis at the key frames
when they are not settled, 0.4-0.7 rad/s of it an offset that wanders: the
map's own shear, which landmarks made with that rate put there and the next
fits match (nothing else ties the rate to the poses; with the settling it is
0.3 rad/s RMS and unbiased, "The frame's own rate"). At 1 m and 14 ms from the middle
row, 1 rad/s puts a landmark 14 mm off, and landmarks persist: drift. Once
the next frame is posed, the central difference of the poses on both sides,
log(T_next T_prev^-1) / (t_next - t_prev), is off by 0.08-0.09 rad/s RMS per
axis there, without bias (docs/fastorb_backend.md, "New landmarks settled
with the poses' rate"). The landmarks are then moved by the change of rate:
p_mid is linear in omega, so the move is -tau_v (d_omega x p_v), in the
world R_cw^T of it. Pure: arrays in, arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from onboard.fastorb.pose import refine_pose
from onboard.fastorb.shutter import back_project, pixels_at_mid, row_times, twist_rate


@dataclass(frozen=True)
class Unsettled:
    """Landmarks made from one posed frame with the rate `omega` (rad/s,
    camera axes): their ids (ascending), camera points p_v as read (before
    the shutter correction), the rows' times tau_v, and the poses around:
    the frame's T_cw at motion time t_s, the previous pose T_prev at t_prev."""

    ids: np.ndarray  # (N,) int64, ascending
    p_C: np.ndarray  # (N, 3) camera points before the shutter correction
    tau_s: np.ndarray  # (N,)
    omega: np.ndarray  # (3,) the rate they were made with
    T_cw: np.ndarray
    t_s: float
    T_prev: np.ndarray
    t_prev: float
    # The frame's own inliers (raw pixels, landmarks, disparity) and its
    # translation rate, to re-pose it with the settled rate (repose); None: not re-posed
    inliers: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None


def unsettled(ids: np.ndarray, uv: np.ndarray, z: np.ndarray, K: np.ndarray, omega: np.ndarray,
              readout_s: float, height_px: int, T_cw: np.ndarray, t_s: float,
              T_prev: np.ndarray, t_prev: float) -> Unsettled:
    """The record `settle` needs for landmarks `ids` made from pixels `uv`
    at depths `z` (the ids come in ascending order from the tracker)."""
    uv = np.asarray(uv, np.float64)
    p = back_project(uv, np.asarray(z, np.float64), K)
    return Unsettled(np.asarray(ids, np.int64), p, row_times(uv[:, 1], readout_s, height_px),
                     np.asarray(omega, np.float64)[:3].copy(), T_cw, t_s, T_prev, t_prev)


def central_rate(u: Unsettled, T_next: np.ndarray, t_next: float) -> np.ndarray:
    """(3,) body rate at the landmarks' frame from the poses on both sides."""
    return twist_rate(u.T_prev, T_next, t_next - u.t_prev)[:3]


def settle(u: Unsettled, omega_new: np.ndarray) -> np.ndarray:
    """(N, 3) world moves of the landmarks `u.ids` when made with `omega_new`
    instead of `u.omega`: R_cw^T (-tau_v (d_omega x p_v)), row-wise."""
    d = np.asarray(omega_new, np.float64) - u.omega
    move_C = -u.tau_s[:, None] * np.cross(d, u.p_C)
    return move_C @ u.T_cw[:3, :3]  # R^T m, row-wise


def reposed_moves(u: Unsettled, omega_new: np.ndarray, K: np.ndarray, readout_s: float,
                  height_px: int, huber_px: float, bf_px: float) -> np.ndarray:
    """(N, 3) world moves of the landmarks `u.ids` when their frame's pose
    is solved again on its inliers' pixels brought to the middle row with
    `omega_new` (no rate fit; the translation rate as before), and they are
    made from that pose with it.

    Why the pose too: the shear fit (shutter.refine_with_rate) frees three
    more parameters per frame, so the pose can follow what is left of the
    map's own shear (the rate and the map's shear are one gauge freedom when
    the view changes little), and a key frame hands that on to every landmark
    it makes: drift. With the rate held at the poses' central difference the
    pose cannot (tum_fr1_rpy, the ground-truth rate for every pose, no fit:
    RPE lag 30 22.9 -> 19.2 mm; docs/fastorb_backend.md "A key frame
    re-posed"). The frame's reported pose keeps the fit, which is less noisy
    from frame to frame."""
    uv, xyz_W, disp, rho = u.inliers
    xi = np.concatenate([np.asarray(omega_new, np.float64)[:3], rho])
    depth = xyz_W @ u.T_cw[2, :3] + u.T_cw[2, 3]
    T = refine_pose(u.T_cw, xyz_W, pixels_at_mid(uv, depth, K, xi, readout_s, height_px), K,
                    huber_px, 5, disp, bf_px)
    p_old = u.p_C - u.tau_s[:, None] * (np.cross(u.omega, u.p_C) + rho)
    p_new = u.p_C - u.tau_s[:, None] * (np.cross(xi[:3], u.p_C) + rho)
    old = (p_old - u.T_cw[:3, 3]) @ u.T_cw[:3, :3]
    new = (p_new - T[:3, 3]) @ T[:3, :3]
    return new - old
