"""FastORB local mapping (issue 18, item 1): per key frame, a local bundle
adjustment over the new key frame and its covisible key frames, then culling.

As ORB-SLAM2's local mapping thread (Mur-Artal and Tardos 2017, Sec. V-B;
Fu et al. Sec. III), which FastORB-SLAM keeps:
  - covisibility: two key frames are linked by the landmarks both observe
    (an edge from min_shared of them); the local window is the new key frame
    and its most covisible ones,
  - local BA (bundle.py, GTSAM) over the window's poses and the landmarks it
    sees; the other key frames seeing those landmarks are fixed anchors,
  - observations left beyond the chi-square gate are erased from their key
    frames, a landmark left without observations is dropped,
  - key-frame culling: a key frame of the window (not the newest, not the
    map's first) whose landmarks are, for at least `redundancy` of them,
    seen by `observers` other key frames, is redundant and removed.

Work is done in units (`step()`): building the problem, one Levenberg-
Marquardt iteration, applying the result. The caller runs one unit in the
idle time after a frame (`FastOrbTracker.backend_step`), so tracking never
waits on it and per-frame tracking cost does not grow; a thread would not do
(GTSAM's binding keeps the GIL while it optimises, bundle.py). A new key
frame made while a BA is running waits for it; only the newest waiting one
is processed (ORB-SLAM2 likewise skips the BA while key frames queue up).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from onboard.core.se3 import inverse
from onboard.fastorb.bundle import BaProblem, BaSettings, LocalBundle
from onboard.fastorb.features import Tracked
from onboard.fastorb.local_map import Keyframe, LocalMap

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MappingSettings:
    local_keyframes: int = 6  # the new key frame and its most covisible ones, optimised
    fixed_keyframes: int = 4  # other key frames seeing the window's landmarks, fixed
    min_shared: int = 15  # landmarks two key frames share for a covisibility edge
    max_points: int = 1000  # landmarks in one BA at most (most observed first)
    redundancy: float = 0.9  # key-frame culling: this share of its landmarks ...
    observers: int = 3  # ... seen by at least this many other key frames


@dataclass(frozen=True)
class Correction:
    """What one local BA changed: landmark positions by id, landmarks dropped."""

    point_ids: np.ndarray  # (M,) sorted
    point_xyz: np.ndarray  # (M, 3)
    dropped_ids: np.ndarray  # landmarks without observations left
    moved_keyframes: tuple[int, ...]
    culled_keyframes: tuple[int, ...]
    delta_W: np.ndarray  # (4, 4) how the newest optimised key frame moved, as a world motion


@dataclass
class _Job:
    bundle: LocalBundle
    rows: np.ndarray  # (N,) row of each observation in its key frame's arrays
    spent_s: float = 0.0


@dataclass
class MappingStats:
    jobs: int = 0
    culled_keyframes: int = 0
    erased_observations: int = 0
    job_ms: list[float] = field(default_factory=list)  # back end time per key frame


class LocalMapping:
    def __init__(self, local_map: LocalMap, K: np.ndarray, ba: BaSettings,
                 s: MappingSettings = MappingSettings()):
        self._map = local_map
        self._K = K
        self._ba = ba
        self.s = s
        self._pending: int | None = None
        self._job: _Job | None = None
        self.stats = MappingStats()

    @property
    def idle(self) -> bool:
        return self._pending is None and self._job is None

    def on_keyframe(self, kf: Keyframe) -> None:
        self._pending = kf.keyframe_id

    def reset(self) -> None:
        """A new map: drop what was pending."""
        self._pending = None
        self._job = None

    def step(self) -> Correction | None:
        """One unit of work; a correction when a BA has just been applied."""
        t0 = time.perf_counter()
        if self._job is None:
            if self._pending is None:
                return None
            kf_id, self._pending = self._pending, None
            self._job = self._build(kf_id)
            if self._job is not None:
                self._job.spent_s += time.perf_counter() - t0
            return None
        job = self._job
        done = job.bundle.step()
        job.spent_s += time.perf_counter() - t0
        if not done:
            return None
        self._job = None
        return self._finish(job)

    # ---------------------------------------------------------------- build
    def _build(self, kf_id: int) -> _Job | None:
        kfs = self._map.keyframes()
        index = {k.keyframe_id: i for i, k in enumerate(kfs)}
        if kf_id not in index or len(kfs) < 2:
            return None
        new = kfs[index[kf_id]]
        shared = np.array([0 if k is new else int(np.isin(np.unique(k.ids), new.ids).sum())
                           for k in kfs])
        order = [i for i in np.argsort(-shared, kind="stable")
                 if shared[i] >= self.s.min_shared][: self.s.local_keyframes - 1]
        local = [index[kf_id]] + order
        lm_ids = np.unique(np.concatenate([kfs[i].ids for i in local]))
        # observations of those landmarks in every key frame
        # One observation per landmark and key frame: a key frame keeps a row
        # per keypoint on a landmark, and keypoints of several pyramid levels
        # sit on one corner (1.6 rows per landmark on figure8). They stay for
        # descriptor matching across scales (re-localisation needs them:
        # circle lost its track without them); the BA counted each as another
        # observation.
        seen = [_first_rows(k.ids, lm_ids) for k in kfs]
        anchors = [i for i in np.argsort([-len(r) for r in seen], kind="stable")
                   if i not in local and len(seen[i]) > 0][: self.s.fixed_keyframes]
        if not anchors:  # the gauge: hold the oldest of the window
            oldest = min(local, key=lambda i: kfs[i].keyframe_id)
            local.remove(oldest)
            anchors = [oldest]
        members = local + anchors
        obs_k = np.concatenate([np.full(len(seen[i]), j) for j, i in enumerate(members)])
        obs_row = np.concatenate([seen[i] for i in members])
        obs_id = np.concatenate([kfs[i].ids[seen[i]] for i in members])
        ids, inverse_idx, counts = np.unique(obs_id, return_inverse=True, return_counts=True)
        keep_lm = counts >= 2  # one observation adds nothing to the poses
        if keep_lm.sum() > self.s.max_points:
            rank = np.argsort(-counts, kind="stable")
            keep_lm[:] = False
            keep_lm[rank[: self.s.max_points]] = True
        o = keep_lm[inverse_idx]
        new_idx = np.cumsum(keep_lm) - 1
        xyz = np.empty((len(ids), 3))
        for i in members:  # the positions all key frames hold agree; take any
            r = seen[i]
            xyz[np.searchsorted(ids, kfs[i].ids[r])] = kfs[i].xyz_W[r]
        uv = np.concatenate([kfs[i].uv[seen[i]] for i in members])
        z = np.concatenate([_depths(kfs[i])[seen[i]] for i in members])
        fixed = np.array([False] * len(local) + [True] * len(anchors))
        problem = BaProblem(
            np.array([kfs[i].keyframe_id for i in members]),
            np.array([kfs[i].T_cw for i in members]), fixed, ids[keep_lm], xyz[keep_lm],
            obs_k[o], new_idx[inverse_idx[o]], uv[o], z[o])
        return _Job(LocalBundle(problem, self._K, self._ba), obs_row[o])

    # ---------------------------------------------------------------- apply
    def _finish(self, job: _Job) -> Correction:
        t0 = time.perf_counter()
        res = job.bundle.result()
        p = job.bundle.problem
        kfs = {k.keyframe_id: k for k in self._map.keyframes()}
        moved = []
        for i in np.flatnonzero(~p.fixed):
            kf = kfs.get(int(p.kf_ids[i]))
            if kf is not None:
                kf.set_pose(res.T_cw[i])
                moved.append(kf.keyframe_id)
        # erase observations beyond the gate; landmarks left with none are dropped
        erase: dict[int, list[int]] = {}
        for n in np.flatnonzero(res.outliers):
            erase.setdefault(int(p.kf_ids[p.obs_kf[n]]), []).append(int(job.rows[n]))
        left = np.bincount(p.obs_lm[~res.outliers], minlength=len(p.lm_ids))
        dropped = p.lm_ids[left == 0]
        keep = left > 0
        ids, xyz = p.lm_ids[keep], res.xyz_W[keep]
        # What was made after the BA was set up (key frames, their new
        # landmarks; the tracked points, the motion model's poses) hangs on
        # the newest optimised key frame: it moves with it, rigidly, so the
        # map stays one consistent piece (a mix of moved and unmoved points
        # would pull the next poses apart).
        newest = int(np.argmax(np.where(p.fixed, -1, p.kf_ids)))
        delta = inverse(res.T_cw[newest]) @ p.T_cw[newest]
        last_id = int(p.kf_ids.max())
        # A landmark of a moved key frame that was not in the BA (seen by it
        # alone, as every landmark is that a key frame makes from its depth,
        # or left out by max_points) moves rigidly with that key frame, the
        # newest observer: where the BA would have put it. Left in place, its
        # copies disagreed with the key frame's new pose and with the tracked
        # points, which follow it (`corrected`).
        done = np.concatenate([ids, dropped])
        extra_ids, extra_xyz = [], []
        for i in sorted(np.flatnonzero(~p.fixed), key=lambda i: -p.kf_ids[i]):
            kf = kfs.get(int(p.kf_ids[i]))
            if kf is None:
                continue
            sel = _first_rows(kf.ids, kf.ids)
            sel = sel[~np.isin(kf.ids[sel], done)]
            d = inverse(res.T_cw[i]) @ p.T_cw[i]
            extra_ids.append(kf.ids[sel])
            extra_xyz.append(kf.xyz_W[sel] @ d[:3, :3].T + d[:3, 3])
            done = np.concatenate([done, kf.ids[sel]])
        ids = np.concatenate([ids, *extra_ids])
        xyz = np.concatenate([xyz, *extra_xyz])
        order = np.argsort(ids, kind="stable")
        ids, xyz = ids[order], xyz[order]
        for kf in kfs.values():
            rows = erase.get(kf.keyframe_id)
            if rows:
                kf.drop_rows(np.array(rows))
            kf.drop_ids(dropped)
            if kf.keyframe_id > last_id:
                kf.set_pose(kf.T_cw @ inverse(delta))
                kf.transform_points(delta, exclude=ids)
            kf.move_points(ids, xyz)
        culled = self._cull(moved)
        self._map.changed()
        self.stats.jobs += 1
        self.stats.erased_observations += int(res.outliers.sum())
        self.stats.culled_keyframes += len(culled)
        self.stats.job_ms.append((job.spent_s + time.perf_counter() - t0) * 1e3)
        log.debug("local BA: %d key frames (%d fixed), %d points, %d observations, %d erased, "
                  "%d iterations, error %.1f -> %.1f; culled %s", len(p.kf_ids), int(p.fixed.sum()),
                  len(p.lm_ids), len(p.obs_kf), int(res.outliers.sum()), res.iterations,
                  res.error_before, res.error_after, culled)
        return Correction(ids, xyz, dropped, tuple(moved), tuple(culled), delta)

    def _cull(self, candidates: list[int]) -> list[int]:
        """ORB-SLAM2's 90 % rule over the window's key frames (not the newest,
        not the first of the map)."""
        kfs = self._map.keyframes()
        if len(kfs) < 3:
            return []
        all_ids = np.concatenate([np.unique(k.ids) for k in kfs])  # observers, once each
        uniq, counts = np.unique(all_ids, return_counts=True)
        newest = kfs[-1].keyframe_id
        first = min(k.keyframe_id for k in kfs)
        culled = []
        for k in kfs:
            if k.keyframe_id not in candidates or k.keyframe_id in (newest, first) or not len(k.ids):
                continue
            own = np.unique(k.ids)
            others = counts[np.searchsorted(uniq, own)] - 1
            if np.mean(others >= self.s.observers) >= self.s.redundancy:
                culled.append(k.keyframe_id)
                counts[np.searchsorted(uniq, own)] -= 1
        for kf_id in culled:
            self._map.remove(kf_id)
        return culled


def corrected(trk: Tracked, c: Correction) -> Tracked:
    """The tracked points after a local BA: at their landmarks' new positions
    (by id), the others moved with the newest optimised key frame, without
    the landmarks it dropped."""
    keep = ~np.isin(trk.ids, c.dropped_ids)
    trk = trk if keep.all() else trk.subset(keep)
    if not len(trk):
        return trk
    xyz = trk.xyz_W @ c.delta_W[:3, :3].T + c.delta_W[:3, 3]
    if len(c.point_ids):
        pos = np.minimum(np.searchsorted(c.point_ids, trk.ids), len(c.point_ids) - 1)
        hit = c.point_ids[pos] == trk.ids
        xyz[hit] = c.point_xyz[pos[hit]]
    return Tracked(trk.uv, xyz, trk.ids)


def _first_rows(ids: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """Rows of `ids` holding one of `wanted`, the first row of each id only."""
    _, first = np.unique(ids, return_index=True)
    first.sort()
    return first[np.isin(ids[first], wanted)]


def _depths(kf: Keyframe) -> np.ndarray:
    return kf.z if kf.z is not None else np.zeros(len(kf.ids))
