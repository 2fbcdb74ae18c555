"""KeyframeMap: kept keys, candidates for re-use, and key positions refined
from key-to-key offsets (linear least squares with known rotations)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from onboard.nislam.keymap import KeyframeMap, Measured


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


def _linked_pair(err_m: float = 0.02):
    """Key 0 at the origin, key 1 truly 0.2 m along x but placed `err_m`
    further (the error of the weak match it was started from, which the
    chain offset carries too)."""
    m: KeyframeMap[Key] = KeyframeMap(capacity=8)
    a, b = _key(0), _key(1, (0.2 + err_m, 0, 0))
    m.use(a)
    m.use(b)
    m.add_offset(0, 1, np.array([0.2 + err_m, 0, 0]), VAR * 100)
    return m, a, b


def test_link_ties_the_current_key_to_the_kept_one_in_view():
    """A frame truly at x = 0.25 m, measured firmly against key 1 (through
    its misplaced position: 0.27 m) and against key 0 (0.25 m): the link's
    offset (0.2 m) is firmer than the chain's and the keys end up 0.2 m
    apart, each moved by half the 20 mm (the gauge keeps their mean). The
    sign matters: an offset taken the wrong way round would put them 0.24 m
    apart, or be refused as a look-alike."""
    m, a, b = _linked_pair()
    asked = []

    def measure(other):
        asked.append(other.keyframe_id)
        return Measured(other.p_W_m + np.array([0.25, 0, 0]), VAR, 200.0)

    R = np.eye(3)
    got = m.link(b, Measured(np.array([0.27, 0, 0]), VAR, 300.0), R, 25.0, 0.5, 30.0, measure)
    assert got is a and asked == [0]
    assert b.p_W_m[0] - a.p_W_m[0] == pytest.approx(0.2, abs=1e-3)
    assert a.p_W_m[0] == pytest.approx(0.01, abs=1e-3)  # mean kept: (0 + 0.22) / 2


@pytest.mark.parametrize("psr, through_other_m", [(20.0, 0.25), (200.0, 0.12)])
def test_link_refuses_a_weak_or_look_alike_second_match(psr, through_other_m):
    """A second match below min_psr, or one that puts the keys 0.15 m
    closer than they are (a look-alike peak, not drift), changes nothing."""
    m, a, b = _linked_pair()

    def measure(other):
        return Measured(other.p_W_m + np.array([through_other_m, 0, 0]), VAR, psr)

    got = m.link(b, Measured(np.array([0.27, 0, 0]), VAR, 300.0), np.eye(3), 25.0, 0.5, 30.0,
                 measure)
    assert got is None
    np.testing.assert_array_equal(a.p_W_m, [0, 0, 0])
    np.testing.assert_array_equal(b.p_W_m, [0.22, 0, 0])


def test_link_needs_a_kept_key_in_view():
    """Key 0 looks 60 deg away: not measured, nothing linked."""
    m, a, b = _linked_pair()
    a.R_W_C = Rotation.from_euler("y", 60.0, degrees=True).as_matrix()
    got = m.link(b, Measured(np.array([0.27, 0, 0]), VAR, 300.0), np.eye(3), 25.0, 0.5, 30.0,
                 lambda other: pytest.fail("a key out of view was measured"))
    assert got is None
