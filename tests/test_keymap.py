"""KeyframeMap: kept keys, candidates for re-use, and key positions refined
from key-to-key offsets (linear least squares with known rotations)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from onboard.nislam.keymap import KeyframeMap


@dataclass
class Key:
    keyframe_id: int
    p_W_m: np.ndarray
    R_W_C: np.ndarray


def _key(i: int, p=(0.0, 0.0, 0.0), yaw_deg: float = 0.0) -> Key:
    R = Rotation.from_euler("y", yaw_deg, degrees=True).as_matrix()  # optical axis z turns about y
    return Key(i, np.array(p, dtype=np.float64), R)


VAR = np.full(3, 1e-6)  # 1 mm standard deviation per axis


def test_loop_offset_removes_the_drift_of_a_key_chain():
    """Keys 0..3 on a square of 0.4 m; each chained offset is measured exactly
    but the keys were placed with a drift of 10 mm per key (what dead
    reckoning from key to key leaves). One offset from key 3 back to key 0
    closes the loop: the firm loop offset wins over the weak chain, whose
    offsets take equal shares of the 30 mm misclosure; that puts the keys
    back in their true arrangement. The weak priors are the gauge: the keys'
    mean position stays where it was."""
    true = np.array([[0, 0, 0], [0.4, 0, 0], [0.4, 0, 0.4], [0, 0, 0.4]], dtype=float)
    drift = np.array([[0, 0, 0], [0.01, 0, 0], [0.02, 0, 0], [0.03, 0, 0]])
    m: KeyframeMap[Key] = KeyframeMap(capacity=8)
    keys = [_key(i, true[i] + drift[i]) for i in range(4)]
    for k in keys:
        m.use(k)
    # chain offsets as measured when each key was started: they carry the drift
    for i in range(3):
        m.add_offset(i, i + 1, true[i + 1] - true[i] + (drift[i + 1] - drift[i]), VAR * 100)
    m.add_offset(3, 0, true[0] - true[3], VAR)  # the loop closure, measured firmly
    moved = m.solve()
    p = np.array([k.p_W_m for k in keys])
    assert moved == pytest.approx(0.015, abs=1e-3)  # keys 0 and 3, by half the drift each
    np.testing.assert_allclose(p - p.mean(axis=0), true - true.mean(axis=0), atol=1e-4)
    np.testing.assert_allclose(p.mean(axis=0), (true + drift).mean(axis=0), atol=1e-6)


def test_consistent_offsets_keep_positions():
    true = np.array([[0, 0, 0], [0.3, 0.1, 0], [0.5, 0.1, 0.2]], dtype=float)
    m: KeyframeMap[Key] = KeyframeMap(capacity=8)
    keys = [_key(i, true[i]) for i in range(3)]
    for k in keys:
        m.use(k)
    m.add_offset(0, 1, true[1] - true[0], VAR)
    m.add_offset(2, 1, true[1] - true[2], VAR)  # given either way round
    m.add_offset(0, 2, true[2] - true[0], VAR)
    assert m.solve() < 1e-7  # float round-off of a system conditioned ~1e8
    np.testing.assert_allclose([k.p_W_m for k in keys], true, atol=1e-7)


def test_repeated_offsets_merge_by_information():
    """Two measurements of the same pair: 10 mm (var 1) and 40 mm (var 3)
    merge to (10/1 + 40/3) / (1/1 + 1/3) = 17.5 mm; a firm prior-free pair
    of keys then sits 17.5 mm apart."""
    m: KeyframeMap[Key] = KeyframeMap(capacity=8)
    a, b = _key(0), _key(1)
    m.use(a)
    m.use(b)
    m.add_offset(0, 1, np.array([0.010, 0, 0]), np.full(3, 1e-8))
    m.add_offset(0, 1, np.array([0.040, 0, 0]), np.full(3, 3e-8))
    m.solve()
    assert b.p_W_m[0] - a.p_W_m[0] == pytest.approx(0.0175, abs=1e-6)


def test_keys_without_offsets_stay_put():
    m: KeyframeMap[Key] = KeyframeMap(capacity=8)
    a, b, c = _key(0), _key(1, (0.1, 0, 0)), _key(2, (5.0, 1.0, 2.0))  # c: after a restart
    for k in (a, b, c):
        m.use(k)
    m.add_offset(0, 1, np.array([0.12, 0, 0]), VAR)
    m.solve()
    np.testing.assert_array_equal(c.p_W_m, [5.0, 1.0, 2.0])
    assert b.p_W_m[0] - a.p_W_m[0] == pytest.approx(0.12, abs=1e-6)


def test_least_recently_used_key_is_evicted_with_its_offsets():
    m: KeyframeMap[Key] = KeyframeMap(capacity=2)
    a, b, c = _key(0), _key(1, (0.1, 0, 0)), _key(2, (0.2, 0, 0))
    m.use(a)
    m.use(b)
    m.add_offset(0, 1, np.array([0.5, 0, 0]), VAR)
    m.use(a)  # a is now the most recently used: b goes when c comes
    m.use(c)
    assert 1 not in m and 0 in m and 2 in m and len(m) == 2
    assert m.solve() == 0.0  # the 0-1 offset went with key 1
    np.testing.assert_array_equal(a.p_W_m, [0, 0, 0])
    m.add_offset(0, 1, np.array([0.5, 0, 0]), VAR)  # to an evicted key: ignored
    assert m.solve() == 0.0


def test_candidates_by_view_and_place():
    m: KeyframeMap[Key] = KeyframeMap(capacity=8)
    keys = [
        _key(0, (0, 0, 0), yaw_deg=0.0),
        _key(1, (0, 0, 0), yaw_deg=20.0),
        _key(2, (0, 0, 0), yaw_deg=5.0),
        _key(3, (0, 0, 0), yaw_deg=40.0),  # looks too far away
        _key(4, (0.8, 0, 0), yaw_deg=0.0),  # too far from here
    ]
    for k in keys:
        m.use(k)
    R = Rotation.from_euler("y", 3.0, degrees=True).as_matrix()
    p = np.array([0.1, 0.0, 0.0])
    found = m.candidates(R, p, exclude_id=0, max_angle_deg=25.0, max_dist_m=0.5, limit=5)
    assert [k.keyframe_id for k in found] == [2, 1]  # 2 deg off, then 17 deg off
    assert [k.keyframe_id for k in m.candidates(R, p, 2, 25.0, 0.5, 1)] == [0]
