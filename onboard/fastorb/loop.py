"""FastORB loop closing (issue 18, item 2), as ORB-SLAM2's loop-closing thread
(Mur-Artal and Tardos 2017, Sec. VI) for RGB-D, which FastORB-SLAM keeps
(Fu et al. Sec. III):

  1. every new key frame is kept as a `KeyRecord` for the whole run (the
     local map forgets key frames after max_keyframes; a loop is exactly
     a return to one it forgot) and queried against the older ones by
     place recognition (place.py: exact Hamming votes, no vocabulary);
     its recent key frames (`min_gap`) and covisible ones (sharing
     `min_shared` landmarks: the local map already holds them) are no
     candidates,
  2. the best-voted candidates are verified by 3-D-3-D RANSAC in SE(3)
     (place.verify), giving the loop edge,
  3. the correction the loop asks for must be one odometry can have
     drifted into: at most `max_shift_m` + `shift_per_m` x the path flown
     between the two key frames (and the same for the turn). A texture
     repeating along a wall matches one period back with a correction of
     a whole period over a path of about one period, far beyond any drift
     (tests/test_fastorb_loop.py),
  4. the essential graph (spanning tree of consecutive key frames, strong
     covisibility links of >= `strong_shared` landmarks, ORB-SLAM2's 100,
     and every accepted loop edge) is optimised on GTSAM (posegraph.py)
     with the loop's old key frame held fixed,
  5. every landmark moves with the key frame that first holds it, the
     duplicates the loop found take their old twins' positions (fusion),
     and the tracker moves its tracked points and motion model with the
     newest key frame (`Correction`, applied as the local BA's is).

It runs one key frame per `step()`, called from `FastOrbTracker.backend_step`
between frames when local mapping is idle, never from `track()`: a
query costs tens of ms, a correction one pose-graph solve; a thread would
not help since GTSAM's binding holds the GIL (bundle.py).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from onboard.core.rotations import so3_log
from onboard.core.se3 import camera_in_world, inverse, se3_log
from onboard.fastorb.local_map import Keyframe, LocalMap
from onboard.fastorb.mapping import Correction
from onboard.fastorb.place import KeyRecord, PlaceIndex, PlaceSettings, Verified, verify
from onboard.fastorb.pose import PnpSettings
from onboard.fastorb.posegraph import Edge, optimise, relative

log = logging.getLogger(__name__)

CHI2_6DOF_99 = 16.81


@dataclass(frozen=True)
class LoopSettings:
    min_gap: int = 20  # the newest key frames are never loop candidates
    min_shared: int = 15  # sharing this many landmarks: a neighbour, not a loop
    strong_shared: int = 100  # covisibility edges of the essential graph (ORB-SLAM2)
    max_shift_m: float = 0.1  # a loop may move the key frame this far ...
    shift_per_m: float = 0.1  # ... plus this share of the path flown since its candidate
    max_turn_deg: float = 5.0  # ... and turn it this far ...
    turn_per_m_deg: float = 2.0  # ... plus this much per metre flown
    min_correction_m: float = 0.005  # smaller (and min_correction_deg) : an edge, no solve
    min_correction_deg: float = 0.3
    after_loop: int = 10  # key frames not queried after a correction (ORB-SLAM2: 10)
    # Each correction is a reset for the flight controller (docs/autopilot.md):
    # at most one per this time; loops found in between wait as edges.
    min_interval_s: float = 3.0
    # A loop must know the relative pose better than the map it corrects:
    # its PnP sd at most this (position of the camera, rotation). A far,
    # small cluster of matches (figure8: 62 points 4 m away in one corner)
    # leaves 4 cm / 0.5 deg; FastORB's own drift here is mm to cm.
    max_sd_m: float = 0.01
    max_sd_deg: float = 0.25
    # Temporal consistency (ORB-SLAM2 asks 3 consecutive key frames): a loop
    # is accepted when one of the previous `consistency_gap` key frames found
    # one asking for the same world correction, within these.
    consistency_gap: int = 3
    consistent_m: float = 0.02  # ... plus consistent_share of the correction
    consistent_deg: float = 0.3
    consistent_share: float = 0.25
    edge_sigma: float = 0.01  # every essential-graph edge alike, rad and m (ORB-SLAM2: identity)
    place: PlaceSettings = PlaceSettings()


@dataclass
class LoopStats:
    queries: int = 0  # key frames queried
    candidates: int = 0  # queries with a place-recognition candidate
    detected: int = 0  # loops verified geometrically (3-D RANSAC)
    accepted: int = 0  # ... and within the drift bound: added to the graph
    corrections: int = 0  # ... and large enough to move the map
    query_ms: list[float] = field(default_factory=list)
    correct_ms: list[float] = field(default_factory=list)


_NO_DESC = np.zeros((0, 32), np.uint8)
_NO_POINTS = np.zeros((0, 3))
_NO_IDS = np.zeros(0, np.int64)


class LoopClosing:
    def __init__(self, local_map: LocalMap, K: np.ndarray, s: LoopSettings = LoopSettings(),
                 enabled: bool = True, pnp: PnpSettings | None = None):
        self._map = local_map
        self._K = K
        self._pnp = pnp
        self.s = s
        self.enabled = enabled  # off: key frames are recorded (their poses), never queried
        self.stats = LoopStats()
        self._rng = np.random.default_rng(0)
        self.reset()

    def reset(self) -> None:
        """A new map: nothing of the old one can close a loop with it."""
        self._records: list[KeyRecord] = []
        self._index: dict[int, int] = {}
        self._times: dict[int, float] = {}
        self._index_words: list[np.ndarray] = []
        self._places = PlaceIndex(self.s.place)
        self._strong: list[tuple[int, int]] = []
        self._loops: list[tuple[int, int, np.ndarray]] = []
        self._pending: deque[int] = deque()
        self._last_loop = -(10**9)  # record index of the last corrected key frame
        self._last_t_s = -np.inf  # its time
        self._hypothesis: tuple[int, np.ndarray] | None = None  # (record, world correction)
        self._moved: dict[int, np.ndarray] = {}  # key frame id -> T_cw, not yet reported

    @property
    def idle(self) -> bool:
        return not self._pending

    def pose_of(self, keyframe_id: int) -> np.ndarray | None:
        """A key frame's T_cw as now estimated; None if not of this map."""
        for kf in reversed(self._map.keyframes()):
            if kf.keyframe_id == keyframe_id:
                return kf.T_cw
        k = self._index.get(keyframe_id)
        return None if k is None else self._records[k].T_cw

    def result_fields(self) -> tuple[int, tuple[tuple[int, np.ndarray, np.ndarray], ...]]:
        """TrackResult's loop_corrections and moved_keyframes (each moved key
        frame reported once, on the next result)."""
        moved = tuple((k, *camera_in_world(T)) for k, T in sorted(self._moved.items()))
        self._moved = {}
        return self.stats.corrections, moved

    def on_keyframe(self, kf: Keyframe) -> None:
        """Keep the new key frame (called from tracking: only what costs
        nothing; hashing and covisibility wait for `step`)."""
        prev = self._records[-1] if self._records else None
        path = 0.0 if prev is None else prev.path_m + float(np.linalg.norm(
            camera_in_world(kf.T_cw)[0] - camera_in_world(prev.T_cw)[0]))
        if self.enabled:
            p_C = kf.xyz_W @ kf.T_cw[:3, :3].T + kf.T_cw[:3, 3]
            # The key frame's arrays are replaced, never written in place: no copies.
            rec = KeyRecord(kf.keyframe_id, kf.T_cw, kf.desc, p_C, kf.ids, path, kf.uv)
        else:  # only its pose is ever read (pose_of): the rest would grow with the flight
            rec = KeyRecord(kf.keyframe_id, kf.T_cw, _NO_DESC, _NO_POINTS, _NO_IDS, path)
        self._index[kf.keyframe_id] = len(self._records)
        self._records.append(rec)
        self._times[kf.keyframe_id] = kf.t_s
        if self.enabled:
            self._pending.append(kf.keyframe_id)

    def points_moved(self, kf: Keyframe) -> None:
        """The key frame's landmarks were moved from their first estimate
        before the back end moved its pose (landmark_rate.py): its record's
        camera points follow, as on_keyframe would have taken them."""
        k = self._index.get(kf.keyframe_id)
        if k is None or self._records[k].T_cw is not kf.T_cw:
            return
        rec = self._records[k]
        if np.array_equal(rec.ids, kf.ids):
            rec.p_C = kf.xyz_W @ kf.T_cw[:3, :3].T + kf.T_cw[:3, 3]

    def _take_in(self, k: int) -> None:
        """Record k (the next in order) into the place index and the strong
        covisibility links with the recent ones."""
        rec = self._records[k]
        for i in range(max(0, k - self.s.min_gap), k):
            if self._shared(i, k) >= self.s.strong_shared:
                self._strong.append((i, k))
        words = self._places.words(rec.desc)
        self._places.add(words)
        self._index_words.append(words)

    def step(self) -> Correction | None:
        """Query one waiting key frame; a correction when a loop moved the map."""
        if not self._pending:
            return None
        t0 = time.perf_counter()
        j = self._index.get(self._pending.popleft())
        if j is None:
            return None
        self._take_in(j)
        self._refresh_poses()
        found = self._detect(j)
        self.stats.query_ms.append((time.perf_counter() - t0) * 1e3)
        if found is None:
            return None
        i, v = found
        self._loops.append((i, j, v.T_ij))
        self.stats.accepted += 1
        shift, turn = self._mismatch(i, j, v)
        log.info("loop: key frame %d with %d (%d of %d matches agree), off by %.3f m, %.2f deg",
                 self._records[j].keyframe_id, self._records[i].keyframe_id, v.inliers,
                 v.matches, shift, turn)
        if shift < self.s.min_correction_m and turn < self.s.min_correction_deg:
            return None
        if not self._significant(i, j, v):
            return None  # within the loop's own uncertainty: an edge, no jump
        t_s = self._times[self._records[j].keyframe_id]
        if t_s - self._last_t_s < self.s.min_interval_s:
            return None  # the edge waits for the next correction
        self._last_t_s = t_s
        t1 = time.perf_counter()
        correction = self._correct(i, v)
        self._last_loop = j
        self.stats.corrections += 1
        self.stats.correct_ms.append((time.perf_counter() - t1) * 1e3)
        return correction

    # ------------------------------------------------------------- detect
    def _detect(self, j: int) -> tuple[int, Verified] | None:
        s = self.s
        n = j - s.min_gap  # records [0, n) may be candidates
        if n <= 0 or j - self._last_loop <= s.after_loop:
            return None
        self.stats.queries += 1
        q = self._records[j]
        scores = self._places.scores(self._index_words[j], j)
        # As ORB-SLAM2: a candidate must look at least as much like the query
        # as the least similar of its covisible recent key frames does.
        near = [k for k in range(n, j) if self._shared(k, j) >= s.min_shared]
        floor = max(s.place.min_score, min((scores[k] for k in near), default=0.0))
        cands = [int(i) for i in np.argsort(-scores[:n], kind="stable")[: 3 * s.place.candidates]
                 if scores[i] >= floor and self._shared(int(i), j) < s.min_shared]
        if not cands:
            return None
        self.stats.candidates += 1
        for i in cands[: s.place.candidates]:
            v = verify(self._records[i], q, s.place, self._rng, self._K, self._pnp)
            if v is None:
                continue
            self.stats.detected += 1
            if not self._firm(v):
                continue
            shift, turn = self._mismatch(i, j, v)
            path = abs(q.path_m - self._records[i].path_m)
            if (shift <= s.max_shift_m + s.shift_per_m * path
                    and turn <= s.max_turn_deg + s.turn_per_m_deg * path):
                return (i, v) if self._consistent(i, j, v) else None
            log.info("loop of key frame %d with %d rejected: a %.2f m / %.1f deg correction "
                     "after %.2f m flown is beyond drift", q.keyframe_id,
                     self._records[i].keyframe_id, shift, turn, path)
        return None

    def _firm(self, v: Verified) -> bool:
        if not np.all(np.isfinite(v.cov)):
            return True  # no covariance (3-D fit only)
        sd_rot = np.sqrt(max(np.linalg.eigvalsh(v.cov[:3, :3]).max(), 0.0))
        sd_pos = np.sqrt(max(np.linalg.eigvalsh(v.cov[3:, 3:]).max(), 0.0))
        return bool(sd_pos <= self.s.max_sd_m and np.degrees(sd_rot) <= self.s.max_sd_deg)

    def _consistent(self, i: int, j: int, v: Verified) -> bool:
        """Whether a recent key frame's loop asked for the same world
        correction. A single verified loop can be a repeated structure seen
        from one place (figure8: 62 of 67 matches agreed on a 0.21 m, 2 deg
        correction against a true 8 mm, 5 sd beyond the PnP covariance);
        from the next key frames it asks for a different one, or none."""
        s = self.s
        D = inverse(inverse(v.T_ij) @ self._records[i].T_cw) @ self._records[j].T_cw
        prev, self._hypothesis = self._hypothesis, (j, D)
        if prev is None or j - prev[0] > s.consistency_gap:
            return False
        diff = inverse(prev[1]) @ D
        size_m = float(np.linalg.norm(D[:3, 3]))
        size_deg = float(np.degrees(np.linalg.norm(so3_log(D[:3, :3]))))
        return (float(np.linalg.norm(diff[:3, 3])) <= s.consistent_m + s.consistent_share * size_m
                and float(np.degrees(np.linalg.norm(so3_log(diff[:3, :3]))))
                <= s.consistent_deg + s.consistent_share * size_deg)

    def _significant(self, i: int, j: int, v: Verified) -> bool:
        """Whether the map's relative pose of the two key frames is off the
        loop's by more than the loop's covariance allows (chi-square, 6 dof,
        99 %), i.e. whether the loop has anything to correct."""
        if not np.all(np.isfinite(v.cov)):
            return True
        T_ji_map = self._records[j].T_cw @ inverse(self._records[i].T_cw)
        xi = se3_log(inverse(v.T_ij) @ inverse(T_ji_map))  # left perturbation of T_ji
        try:
            d2 = float(xi @ np.linalg.solve(v.cov, xi))
        except np.linalg.LinAlgError:
            return True
        return d2 > CHI2_6DOF_99

    def _shared(self, a: int, b: int) -> int:
        return int(np.isin(self._records[a].ids, self._records[b].ids).sum())

    def _mismatch(self, i: int, j: int, v: Verified) -> tuple[float, float]:
        """How far (m, deg) the loop says key frame j is from where the map has it."""
        T_loop = inverse(v.T_ij) @ self._records[i].T_cw
        T_now = self._records[j].T_cw
        shift = float(np.linalg.norm(camera_in_world(T_loop)[0] - camera_in_world(T_now)[0]))
        turn = float(np.degrees(np.linalg.norm(so3_log(T_loop[:3, :3] @ T_now[:3, :3].T))))
        return shift, turn

    # ------------------------------------------------------------ correct
    def _refresh_poses(self) -> None:
        """Key frames still in the local map may have been moved by local BA."""
        for kf in self._map.keyframes():
            k = self._index.get(kf.keyframe_id)
            if k is not None:
                self._records[k].T_cw = kf.T_cw

    def _correct(self, fixed: int, v: Verified) -> Correction:
        recs = self._records
        T_old = np.array([r.T_cw for r in recs])
        sig = np.full(6, self.s.edge_sigma)
        pairs = [(k - 1, k) for k in range(1, len(recs))] + self._strong
        edges = [Edge(a, b, relative(T_old[a], T_old[b]), sig) for a, b in pairs]
        edges += [Edge(a, b, T_ab, sig) for a, b, T_ab in self._loops]
        T_new = optimise(T_old, edges, fixed=fixed)
        moves = np.array([inverse(T_new[k]) @ T_old[k] for k in range(len(recs))])  # world motions
        for k, r in enumerate(recs):
            r.T_cw = T_new[k]
            if np.abs(moves[k] - np.eye(4)).max() > 1e-4:  # ~0.1 mm / 0.006 deg
                self._moved[r.keyframe_id] = T_new[k]
        live = self._map.keyframes()
        slots = [self._index.get(kf.keyframe_id, len(recs) - 1) for kf in live]
        for kf, k in zip(live, slots):
            kf.set_pose(T_new[k])
        # Each landmark moves with the oldest live key frame holding it (the
        # one that made it, or the oldest still kept) ...
        ids = np.concatenate([kf.ids for kf in live]) if live else np.zeros(0, np.int64)
        xyz = np.concatenate([kf.xyz_W for kf in live]) if live else np.zeros((0, 3))
        slot = np.concatenate([np.full(len(kf.ids), k) for kf, k in zip(live, slots)]
                              ) if live else np.zeros(0, np.int64)
        point_ids, first = np.unique(ids, return_index=True)
        M = moves[slot[first]]
        point_xyz = np.einsum("nij,nj->ni", M[:, :3, :3], xyz[first]) + M[:, :3, 3]
        # ... and a duplicate the loop found takes its old twin's position.
        twin = recs[fixed]
        T_wc = inverse(T_new[fixed])
        pos = np.searchsorted(point_ids, v.ids_j)
        ok = (pos < len(point_ids)) & (point_ids[np.minimum(pos, len(point_ids) - 1)] == v.ids_j)
        rows = np.flatnonzero(np.isin(twin.ids, v.ids_i))
        by_id = dict(zip(twin.ids[rows].tolist(), twin.p_C[rows] @ T_wc[:3, :3].T + T_wc[:3, 3]))
        for p, old_id in zip(pos[ok], v.ids_i[ok]):
            point_xyz[p] = by_id[int(old_id)]
        for kf in live:
            kf.move_points(point_ids, point_xyz)
        self._map.changed()
        return Correction(point_ids, point_xyz, np.zeros(0, np.int64),
                          tuple(kf.keyframe_id for kf in live), (), moves[-1])
