"""Pose-graph optimisation for FastORB's loop closing (issue 18, item 2; the
part built so far): key-frame poses tied by relative-pose edges, solved on
GTSAM with `BetweenFactorPose3` and Levenberg-Marquardt.

As ORB-SLAM2's essential-graph optimisation (Mur-Artal and Tardos 2017,
Sec. VI-D) for RGB-D (SE(3), no scale): the edges are the spanning tree of
consecutive key frames and the strong covisibility links, each holding the
relative pose the map had before the loop, plus the loop edges from a
verified loop; one key frame is held fixed. Landmarks then move with the key
frame that made them (`move_points`), so the map stays one piece.

Poses are T_cw (world -> camera) as elsewhere in FastORB; GTSAM's Pose3 of a
camera is T_wc.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from onboard.core.se3 import inverse


@dataclass(frozen=True)
class Edge:
    """Relative pose of key frame j seen from key frame i: T_ci_cj = T_ci_w T_w_cj."""

    i: int
    j: int
    T_ij: np.ndarray  # (4, 4)
    sigmas: np.ndarray  # (6,) rotation [rad] (x, y, z) then translation [m], GTSAM's order


def relative(T_cw_i: np.ndarray, T_cw_j: np.ndarray) -> np.ndarray:
    """T_ci_cj: key frame j's pose in key frame i's axes."""
    return T_cw_i @ inverse(T_cw_j)


def optimise(T_cw: np.ndarray, edges: list[Edge], fixed: int = 0,
             max_iterations: int = 50) -> np.ndarray:
    """The poses (P, 4, 4) that best agree with the edges, key frame `fixed`
    held where it is."""
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k in range(len(T_cw)):
        values.insert(X(k), gtsam.Pose3(inverse(T_cw[k])))
    graph.add(gtsam.NonlinearEqualityPose3(X(fixed), gtsam.Pose3(inverse(T_cw[fixed]))))
    for e in edges:
        graph.add(gtsam.BetweenFactorPose3(X(e.i), X(e.j), gtsam.Pose3(e.T_ij),
                                           gtsam.noiseModel.Diagonal.Sigmas(e.sigmas)))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return np.array([inverse(result.atPose3(X(k)).matrix()) for k in range(len(T_cw))])


def move_points(xyz_W: np.ndarray, T_cw_before: np.ndarray, T_cw_after: np.ndarray) -> np.ndarray:
    """Landmarks of a key frame carried along with it: same place in its camera."""
    p_C = xyz_W @ T_cw_before[:3, :3].T + T_cw_before[:3, 3]
    return (p_C - T_cw_after[:3, 3]) @ T_cw_after[:3, :3]
