"""Place recognition and geometric verification for FastORB's loop closing
(issue 18, item 2).

Recognition needs no vocabulary. ORB-SLAM2 finds loop candidates with a
bag of binary words (DBoW2) whose vocabulary was trained offline on other
images; a vocabulary trained on the sequences we are scored on would not
be honest, and one trained elsewhere is a 40-150 MB file. Key frames here
number in the hundreds, each with a few hundred ORB descriptors, so the
query is done exactly instead: every descriptor of the new key frame is
matched (brute-force Hamming, one cv2 call) against the pooled descriptors
of all older key frames that are not its recent or covisible neighbours,
and each key frame gets a vote per descriptor whose nearest neighbour it
holds within `max_hamming` (ORB-SLAM2's TH_LOW = 50). Cost grows linearly
with the map (measured in docs/fastorb_backend.md); the pool is one
contiguous array, so the query is one SIMD popcount pass.

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

from onboard.core.evaluation import umeyama_se3
from onboard.core.se3 import make_pose


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


@dataclass(frozen=True)
class PlaceSettings:
    max_hamming: int = 50  # a descriptor's nearest neighbour counts this close (ORB-SLAM2 TH_LOW)
    min_votes: int = 30  # a candidate needs this many descriptors voting for it
    candidates: int = 3  # best-voted key frames verified per query
    ratio: float = 0.8  # verification: Lowe's ratio between the two key frames
    ransac_iterations: int = 200
    inlier_floor_m: float = 0.01  # 3-D inlier gate: floor plus 3 sd of two depth readings
    depth_sd: float = 0.0015  # depth sd per m^2 of depth [1/m] (FastOrbParams.local_ba_depth_sd)
    min_inliers: int = 40  # a verified loop needs this many 3-D inliers ...
    min_inlier_share: float = 0.35  # ... and this share of the matches


def vote(query: np.ndarray, pool: np.ndarray, owner: np.ndarray, n_owners: int,
         max_hamming: int) -> np.ndarray:
    """Votes (n_owners,): for each query descriptor, one for the owner of its
    nearest pool descriptor when within max_hamming (each pool descriptor
    counted once, so a repeated query texture does not pile up votes)."""
    if not len(query) or not len(pool):
        return np.zeros(n_owners, np.int64)
    matches = cv2.BFMatcher(cv2.NORM_HAMMING).match(query, pool)
    hit = np.unique([m.trainIdx for m in matches if m.distance <= max_hamming])
    return np.bincount(owner[hit.astype(np.int64)], minlength=n_owners)


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
    ids_i: np.ndarray  # landmark ids of the inlier pairs, candidate side
    ids_j: np.ndarray  # ... query side


def verify(cand: KeyRecord, query: KeyRecord, s: PlaceSettings,
           rng: np.random.Generator) -> Verified | None:
    """3-D-3-D RANSAC between two key frames' landmarks (each in its camera);
    None when fewer than min_inliers (or min_inlier_share) agree."""
    ia, ib = ratio_matches(cand.desc, query.desc, s.ratio, s.max_hamming)
    if len(ia) < s.min_inliers:
        return None
    P, Q = cand.p_C[ia], query.p_C[ib]  # P ~ R Q + t
    # Two depth readings, each sd k z^2; 3 sd of their difference, plus a floor.
    gate2 = (s.inlier_floor_m + 3.0 * np.sqrt(2.0) * s.depth_sd * P[:, 2] ** 2) ** 2
    best = np.zeros(len(P), bool)
    for _ in range(s.ransac_iterations):
        pick = rng.choice(len(P), 3, replace=False)
        if np.linalg.matrix_rank(P[pick] - P[pick].mean(0), tol=1e-2) < 2:
            continue  # (nearly) collinear: no rotation from it
        R, t = umeyama_se3(Q[pick], P[pick])
        inl = np.sum((Q @ R.T + t - P) ** 2, axis=1) <= gate2
        if inl.sum() > best.sum():
            best = inl
    for _ in range(2):  # refit on the inliers, take the inliers of the refit
        if best.sum() < max(s.min_inliers, 3):
            return None
        R, t = umeyama_se3(Q[best], P[best])
        best = np.sum((Q @ R.T + t - P) ** 2, axis=1) <= gate2
    n = int(best.sum())
    if n < s.min_inliers or n < s.min_inlier_share * len(P):
        return None
    return Verified(make_pose(R, t), n, len(P), cand.ids[ia[best]], query.ids[ib[best]])
