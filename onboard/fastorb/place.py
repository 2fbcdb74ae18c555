"""Place recognition and geometric verification for FastORB's loop closing
(issue 18, item 2).

Recognition needs no trained vocabulary. ORB-SLAM2 finds loop candidates
with a bag of binary words (DBoW2) whose vocabulary was trained offline on
other images (a 40-150 MB file); one trained on the sequences we are scored
on would not be honest. Here the words come from locality-sensitive
hashing (Gionis, Indyk, Motwani 1999, bit sampling for Hamming space):
each of `tables` hash tables takes the same `bits` fixed random bit
positions of every 256-bit ORB descriptor, and those bits are the word.
The same point seen again differs in ~10-15 % of its bits, so it keeps a
table's word with probability ~0.87^16 = 0.11, about one word in 8 tables;
two unrelated descriptors share one with probability 8 x 2^-16. Key frames
are scored against the query by the cosine of their idf-weighted binary
word vectors (idf from the key frames so far: words common to many views,
from biased ORB bits, weigh little), one sparse product for all of them.
Exact matching against every key frame was tried first: 800 query
descriptors against 100 000 took 8.9 s on the loaded 2-core machine.

Verification (RGB-D: the depth fixes the scale, so SE(3), not Sim(3) as
for monocular ORB-SLAM): ratio-test matches between the two key frames'
descriptors, each landmark in its own key frame's camera coordinates,
then RANSAC on 3-point rigid fits (Umeyama 1991, no scale) with a depth-
noise inlier gate, refit on the inliers. The result is the relative pose
T_ci_cj between the candidate i and the query j: the loop edge.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import csr_matrix

from onboard.core.evaluation import umeyama_se3
from onboard.core.se3 import inverse, make_pose
from onboard.fastorb.pose import PnpSettings, solve_pnp


@dataclass
class KeyRecord:
    """What loop closing keeps of a key frame, for as long as the run lasts
    (the local map forgets key frames; this does not): its pose (updated by
    the back end), descriptors and landmarks in its own camera axes."""

    keyframe_id: int
    T_cw: np.ndarray  # (4, 4), the current estimate
    desc: np.ndarray  # (N, 32) uint8
    p_C: np.ndarray  # (N, 3) landmarks in the key frame's camera [m]
    ids: np.ndarray  # (N,) landmark ids
    path_m: float  # distance flown from the map's first key frame to this one
    uv: np.ndarray | None = None  # (N, 2) the landmarks' pixels in the key frame


@dataclass(frozen=True)
class PlaceSettings:
    tables: int = 8  # hash tables (words per descriptor)
    bits: int = 16  # descriptor bits per word
    min_score: float = 0.02  # a candidate scores at least this (and its covisible ones' least)
    candidates: int = 3  # best-scored key frames verified per query
    max_hamming: int = 50  # verification: matches this close at most (ORB-SLAM2 TH_LOW)
    ratio: float = 0.8  # verification: Lowe's ratio between the two key frames
    ransac_iterations: int = 200
    inlier_floor_m: float = 0.01  # 3-D inlier gate: floor plus 3 sd of two depth readings
    depth_sd: float = 0.0015  # depth sd per m^2 of depth [1/m] (FastOrbParams.local_ba_depth_sd)
    min_inliers: int = 40  # a verified loop needs this many 3-D inliers ...
    min_inlier_share: float = 0.35  # ... and this share of the matches


class PlaceIndex:
    """Bags of hashed binary words of the key frames, in insertion order."""

    def __init__(self, s: PlaceSettings, seed: int = 0):
        rng = np.random.default_rng(seed)
        self._sel = np.array([rng.choice(256, s.bits, replace=False) for _ in range(s.tables)])
        self._pow = (1 << np.arange(s.bits)).astype(np.int64)
        self._offset = (np.arange(s.tables, dtype=np.int64) << s.bits)[None, :]
        self._size = s.tables << s.bits
        self._rows: list[np.ndarray] = []  # sorted unique words of each key frame
        self._df = np.zeros(self._size, np.int64)  # key frames holding each word

    def words(self, desc: np.ndarray) -> np.ndarray:
        bits = np.unpackbits(np.ascontiguousarray(desc, np.uint8), axis=1).astype(np.int64)
        return np.unique((bits[:, self._sel] @ self._pow) + self._offset)

    def add(self, words: np.ndarray) -> None:
        self._rows.append(words)
        self._df[words] += 1

    def scores(self, words: np.ndarray, n: int) -> np.ndarray:
        """Cosine similarity (n,) of the query's words with key frames [0, n)."""
        if n <= 0 or not len(words):
            return np.zeros(max(n, 0))
        idf2 = np.log((len(self._rows) + 1.0) / (self._df + 1.0)) ** 2
        rows = self._rows[:n]
        indptr = np.concatenate([[0], np.cumsum([len(r) for r in rows])])
        M = csr_matrix((np.ones(indptr[-1]), np.concatenate(rows), indptr), (n, self._size))
        q = np.zeros(self._size)
        q[words] = idf2[words]
        norm = np.sqrt(M @ idf2) * np.sqrt(q.sum())
        return (M @ q) / np.maximum(norm, 1e-12)


def ratio_matches(a: np.ndarray, b: np.ndarray, ratio: float, max_hamming: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (ia, ib): a's descriptors matched into b with Lowe's ratio
    test, each b used once (the closer match kept)."""
    if len(a) < 2 or len(b) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    knn = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(a, b, k=2)
    pairs = [(m[0].distance, m[0].queryIdx, m[0].trainIdx) for m in knn
             if len(m) == 2 and m[0].distance <= max_hamming
             and m[0].distance < ratio * m[1].distance]
    pairs.sort()
    used: set[int] = set()
    ia, ib = [], []
    for _, q, t in pairs:
        if t not in used:
            used.add(t)
            ia.append(q)
            ib.append(t)
    return np.array(ia, np.int64), np.array(ib, np.int64)


@dataclass(frozen=True)
class Verified:
    T_ij: np.ndarray  # (4, 4) query j's camera in candidate i's: p_i = T_ij p_j
    inliers: int
    matches: int
    cov: np.ndarray  # (6, 6) of T_ji = inverse(T_ij), left perturbation (phi, rho); NaN: none
    ids_i: np.ndarray  # landmark ids of the inlier pairs, candidate side
    ids_j: np.ndarray  # ... query side


def verify(cand: KeyRecord, query: KeyRecord, s: PlaceSettings, rng: np.random.Generator,
           K: np.ndarray | None = None, pnp: PnpSettings | None = None) -> Verified | None:
    """3-D-3-D RANSAC between two key frames' landmarks (each in its camera);
    then, with K and the query's pixels, the tracker's PnP (pose.solve_pnp:
    pixels and the query's depths as disparities) on the 3-D inliers, which
    also gives the loop's covariance. Far depths are loose (k z^2: 2.4 cm at
    4 m), so a 3-D fit on a far cluster is off by 10-20 cm and 1-2 deg while
    its pixels agree within 1 px with either pose (figure8: a loop off by
    0.16 m against a true 4 mm): the covariance says so. None when fewer
    than min_inliers (or min_inlier_share) agree."""
    ia, ib = ratio_matches(cand.desc, query.desc, s.ratio, s.max_hamming)
    if len(ia) < s.min_inliers:
        return None
    P, Q = cand.p_C[ia], query.p_C[ib]  # P ~ R Q + t
    # Two depth readings, each sd k z^2; 3 sd of their difference, plus a floor.
    gate2 = (s.inlier_floor_m + 3.0 * np.sqrt(2.0) * s.depth_sd * P[:, 2] ** 2) ** 2
    best = np.zeros(len(P), bool)
    needed = s.ransac_iterations
    it = 0
    while it < needed:
        it += 1
        pick = rng.choice(len(P), 3, replace=False)
        if np.linalg.matrix_rank(P[pick] - P[pick].mean(0), tol=1e-2) < 2:
            continue  # (nearly) collinear: no rotation from it
        R, t = umeyama_se3(Q[pick], P[pick])
        inl = np.sum((Q @ R.T + t - P) ** 2, axis=1) <= gate2
        if inl.sum() > best.sum():
            best = inl
            # Adaptive stop (Hartley and Zisserman, Sec. 4.7.1): enough samples
            # for a 99.9 % chance that one was all inliers.
            w3 = min((best.sum() / len(P)) ** 3, 1.0 - 1e-9)
            needed = min(s.ransac_iterations, int(np.ceil(np.log(1e-3) / np.log(1.0 - w3))))
    for _ in range(2):  # refit on the inliers, take the inliers of the refit
        if best.sum() < max(s.min_inliers, 3):
            return None
        R, t = umeyama_se3(Q[best], P[best])
        best = np.sum((Q @ R.T + t - P) ** 2, axis=1) <= gate2
    T_ij, cov = make_pose(R, t), np.full((6, 6), np.nan)
    if K is not None and query.uv is not None:
        sel = np.flatnonzero(best)
        fit = solve_pnp(P[sel], query.uv[ib[sel]], K, pnp or PnpSettings(), s.min_inliers,
                        Q[sel, 2])
        if fit is None:
            return None
        best = np.zeros(len(P), bool)
        best[sel[fit.inliers]] = True
        T_ij, cov = inverse(fit.T_cw), fit.cov
    n = int(best.sum())
    if n < s.min_inliers or n < s.min_inlier_share * len(P):
        return None
    return Verified(T_ij, n, len(P), cov, cand.ids[ia[best]], query.ids[ib[best]])
