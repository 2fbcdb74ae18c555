"""Pose graph on GTSAM (onboard/fastorb/posegraph.py): an artificial loop with
a known drift is closed."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from onboard.core.se3 import inverse, make_pose
from onboard.fastorb.posegraph import Edge, move_points, optimise, relative


def _circle(n: int) -> np.ndarray:
    """T_cw of n cameras on a 2 m circle, each turned by 360/n deg about y."""
    T = []
    for k in range(n):
        yaw = np.radians(360.0 * k / n)
        R = Rotation.from_rotvec([0.0, yaw, 0.0]).as_matrix()
        c = np.array([2.0 * np.sin(np.radians(360.0 * k / n)), 0.0,
                      2.0 - 2.0 * np.cos(np.radians(360.0 * k / n))])
        T.append(inverse(make_pose(R, c)))
    return np.array(T)


def _drifted(truth: np.ndarray, drift_deg: float) -> np.ndarray:
    """Odometry: the true steps chained, each with a yaw error of drift_deg."""
    err = make_pose(Rotation.from_rotvec([0.0, np.radians(drift_deg), 0.0]).as_matrix(),
                    np.zeros(3))
    out = [truth[0]]
    for k in range(len(truth) - 1):
        step = relative(truth[k], truth[k + 1]) @ err
        out.append(inverse(step) @ out[-1])
    return np.array(out)


def test_loop_edge_removes_the_drift_and_points_follow() -> None:
    """Odometry edges that drift 0.5 deg per step (a 10 deg and ~0.5 m error
    at the end of a 20-step loop) and one exact loop edge from the last
    key frame back to the first: after optimisation every pose is within
    2 cm / 0.5 deg of the truth (the drift was spread along the loop), a
    landmark moves with its key frame, and without the loop edge nothing
    changes."""
    n = 20
    truth = _circle(n)
    drifted = _drifted(truth, 0.5)
    odo_sig = np.array([0.01, 0.01, 0.01, 0.02, 0.02, 0.02])
    edges = [Edge(k, k + 1, relative(drifted[k], drifted[k + 1]), odo_sig) for k in range(n - 1)]
    end_error = np.linalg.norm(inverse(drifted[-1])[:3, 3] - inverse(truth[-1])[:3, 3])
    assert end_error > 0.3
    same = optimise(drifted, edges)
    assert np.allclose(same, drifted, atol=1e-6)
    loop = Edge(n - 1, 0, relative(truth[n - 1], truth[0]), odo_sig / 10)
    fixed = optimise(drifted, edges + [loop])
    pos = [np.linalg.norm(inverse(fixed[k])[:3, 3] - inverse(truth[k])[:3, 3]) for k in range(n)]
    rot = [np.degrees(np.linalg.norm(Rotation.from_matrix(
        fixed[k][:3, :3] @ truth[k][:3, :3].T).as_rotvec())) for k in range(n)]
    assert max(pos) < 0.02 and max(rot) < 0.5, (max(pos), max(rot))
    assert np.allclose(fixed[0], drifted[0])  # the anchor
    p_W = inverse(drifted[-1])[:3, :3] @ np.array([0.1, 0.2, 1.5]) + inverse(drifted[-1])[:3, 3]
    moved = move_points(p_W[None], drifted[-1], fixed[-1])[0]
    p_true = inverse(truth[-1])[:3, :3] @ np.array([0.1, 0.2, 1.5]) + inverse(truth[-1])[:3, 3]
    assert np.linalg.norm(moved - p_true) < 0.03
