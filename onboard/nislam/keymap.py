"""Key frames kept for re-use, and their positions refined as a linear graph.

NI-SLAM poses every frame against one key and starts a new key when the
match weakens (PSR < T_r, Eq. 17); each new key inherits the pose error of the
frame that started it, so errors add up key after key. A drone hovering and
looking around, or a hand-held camera sweeping back and forth, keeps coming
back to views it has keys for. `KeyframeMap` keeps the recent keys; when the
current key weakens (or, after a firm frame's pose, the view is about to leave
its grid), the tracker first tries the keys that look the same way
from about the same place, and re-uses one that matches well instead of
starting a new key.

A frame matched against two keys (the weakening current one and a re-used
one) measures the offset between the two key positions. With the attitude
from the AHRS, key orientations are known, so refining the key positions from
such offsets is a linear least-squares problem (translation averaging with
known rotations): one small solve, no iterations, in keeping with the
method. Offsets measured more than once between the same two keys are merged
into their information-weighted mean, so the graph stays bounded by the
number of keys kept. Such offsets are also measured between re-uses
(`link`): every few frames a firm match is repeated against the kept key
most alike in view, so the keys already agree when one is re-used.

Pure: numpy in and out, no threads, no I/O. The keys are the tracker's own
objects; the map only reads `keyframe_id`, `R_W_C` and reads and writes
`p_W_m` (in place, so the tracker sees refined positions at once).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Generic, Protocol, TypeVar

import numpy as np


class MapKey(Protocol):
    keyframe_id: int
    p_W_m: np.ndarray  # (3,), refined in place by KeyframeMap.solve
    R_W_C: np.ndarray  # (3, 3)


K = TypeVar("K", bound=MapKey)

# Gauge: every key is held weakly (10 m of standard deviation: it never
# competes with an offset) at its current position, which keeps the system
# solvable (keys no offset ties to the rest, after a restart, stay put) and
# keeps the mean position of each connected group of keys where it was, so a
# loop closure shares its correction between the old and the new keys and the
# current position jumps the least. Holding the oldest key fixed instead, as
# pose graphs often do, scored worse on tum_fr1_rpy (ATE 0.0368 against
# 0.0337 m, and worse from each of starts 1, 2, 3, 5 by 2-4 mm): the first
# keys are made while the time-offset calibration is still settling.
_PRIOR_VAR_M2 = 100.0

# A link (see KeyframeMap.link) whose offset disagrees with the two keys'
# positions by more than this is taken for a look-alike peak, not drift: the
# kept keys of tum_fr1_rpy disagree with the chain by ~2 cm RMS (48 mm at
# most), a wrong peak by the search window (10 cm and more).
LINK_MAX_DISAGREEMENT_M = 0.1


@dataclass(frozen=True)
class Measured:
    """A frame measured against a key: its world position through that key,
    the per-axis variances (world axes) and the match's PSR."""

    p_W_m: np.ndarray
    var_W_m2: np.ndarray
    psr: float


@dataclass
class _Offset:
    """Information-weighted sums of the measured p_j - p_i (world axes)."""

    info: np.ndarray  # (3,) sum of 1 / var
    info_d: np.ndarray  # (3,) sum of d / var


class KeyframeMap(Generic[K]):
    """At most `capacity` keys (the least recently used go first) and the
    offsets measured between them."""

    def __init__(self, capacity: int, on_evict: Callable[[K], None] | None = None) -> None:
        """`on_evict` is called with each key the map lets go of."""
        self.capacity = capacity
        self._on_evict = on_evict
        self._keys: dict[int, K] = {}  # insertion order = least recently used first
        self._offsets: dict[tuple[int, int], _Offset] = {}

    def __len__(self) -> int:
        return len(self._keys)

    def __contains__(self, keyframe_id: int) -> bool:
        return keyframe_id in self._keys

    def keys(self) -> list[K]:
        return list(self._keys.values())

    def use(self, key: K) -> None:
        """Add `key` (or mark it most recently used); evicts beyond capacity."""
        self._keys.pop(key.keyframe_id, None)
        self._keys[key.keyframe_id] = key
        while len(self._keys) > self.capacity:
            self._evict(next(iter(self._keys)))

    def candidates(
        self, R_W_C: np.ndarray, p_W_m: np.ndarray, exclude_id: int, max_angle_deg: float,
        max_dist_m: float, limit: int,
    ) -> list[K]:
        """Keys other than `exclude_id` whose optical axis is within
        `max_angle_deg` of this camera's and whose position is within
        `max_dist_m` of `p_W_m`, the most alike in view first."""
        cos_min = math.cos(math.radians(max_angle_deg))
        axis = R_W_C[:, 2]
        found = []
        for k in self._keys.values():
            if k.keyframe_id == exclude_id:
                continue
            cos_a = float(k.R_W_C[:, 2] @ axis)
            if cos_a >= cos_min and float(np.linalg.norm(k.p_W_m - p_W_m)) <= max_dist_m:
                found.append((-cos_a, k.keyframe_id, k))
        found.sort(key=lambda x: (x[0], x[1]))
        return [k for _, _, k in found[:limit]]

    def add_offset(self, i: int, j: int, d_W_m: np.ndarray, var_W_m2: np.ndarray) -> None:
        """A measurement of p_j - p_i with per-axis variances (world axes)."""
        if i == j or i not in self._keys or j not in self._keys:
            return
        if i > j:
            i, j, d_W_m = j, i, -np.asarray(d_W_m)
        info = 1.0 / np.maximum(np.asarray(var_W_m2, dtype=np.float64), 1e-12)
        o = self._offsets.get((i, j))
        if o is None:
            self._offsets[(i, j)] = _Offset(info.copy(), info * d_W_m)
        else:
            o.info += info
            o.info_d += info * d_W_m

    def link(
        self, key: K, at_key: Measured, R_W_C: np.ndarray, max_angle_deg: float,
        max_dist_m: float, min_psr: float, measure: Callable[[K], Measured | None],
    ) -> K | None:
        """Tie `key` to the kept key most alike in view of a frame firmly
        matched against it (`at_key`): `measure(other)` matches the same
        frame against that key. A firm second match (PSR >= `min_psr`) is an
        offset between the two keys, as at a re-use, and the key positions are
        solved again. Made while both keys are in view, the keys agree before
        one is re-used (the re-use then moves the position by a fraction of
        what it did, docs/nislam-error-budget.md), and the current key, made
        from the weakest match of its predecessor (PSR < T_r, Eq. 17), is
        measured against the other keys too, not only through that match.
        Returns the key linked, or None."""
        d_key = at_key.p_W_m - key.p_W_m
        for other in self.candidates(R_W_C, at_key.p_W_m, key.keyframe_id, max_angle_deg,
                                     max_dist_m, 1):
            at_other = measure(other)
            if at_other is None or not at_other.psr >= min_psr:
                continue
            d = d_key - (at_other.p_W_m - other.p_W_m)  # other - key, measured
            if float(np.linalg.norm(d - (other.p_W_m - key.p_W_m))) > LINK_MAX_DISAGREEMENT_M:
                continue
            self.add_offset(key.keyframe_id, other.keyframe_id, d,
                            at_key.var_W_m2 + at_other.var_W_m2)
            self.solve()
            return other
        return None

    def solve(self) -> float:
        """Refine every key position from the offsets (weighted linear least
        squares per axis, each key held weakly where it is);
        returns the largest move [m]."""
        ids = list(self._keys)
        n = len(ids)
        if n < 2 or not self._offsets:
            return 0.0
        col = {k: c for c, k in enumerate(ids)}
        p = np.array([self._keys[k].p_W_m for k in ids], dtype=np.float64)  # (n, 3)
        moved = 0.0
        for ax in range(3):
            h = np.eye(n) / _PRIOR_VAR_M2
            b = p[:, ax] / _PRIOR_VAR_M2
            for (i, j), o in self._offsets.items():
                a, c = col[i], col[j]
                w = o.info[ax]
                d = o.info_d[ax] / w
                h[a, a] += w
                h[c, c] += w
                h[a, c] -= w
                h[c, a] -= w
                b[c] += w * d
                b[a] -= w * d
            x = np.linalg.solve(h, b)
            moved = max(moved, float(np.max(np.abs(x - p[:, ax]))))
            for k, xk in zip(ids, x):
                self._keys[k].p_W_m[ax] = xk
        return moved

    def _evict(self, keyframe_id: int) -> None:
        key = self._keys.pop(keyframe_id)
        for pair in [pr for pr in self._offsets if keyframe_id in pr]:
            del self._offsets[pair]
        if self._on_evict is not None:
            self._on_evict(key)
