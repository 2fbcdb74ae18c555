"""Keypoint correspondences for FastORB: the descriptor-free two-stage matcher
between adjacent frames (Sec. IV of Fu et al.) and descriptor matching
against key frames.

Stage one: pyramid Lucas-Kanade seeded with predicted positions (Algorithms
1-2, Eqs. 16-20). Stage two: grid motion statistics (GMS, Bian et al.) then
RANSAC on the fundamental matrix (Sec. IV-D). All functions are pure.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from onboard.fastorb.kernels import gms_keep, one_to_one, radius_pairs

# GMS's four grid placements: the left grid moved by no or half a cell in x
# and in y, independently.
_HALF_SHIFTS = (0.0, 0.5)


@dataclass(frozen=True)
class LkSettings:
    """Pyramid LK as used by FastORB (Algorithm 2).

    `win_px`: integration window side (the paper's omega = 2 is 5 x 5 = 25
    pixels, k of Eq. 17). `max_level`: OpenCV pyramid levels above the image.
    `max_iter`: N_itermax of Eq. 20. `eps_px`: OpenCV stops when an update
    moves less than this. `max_error`: Eq. 19's mean absolute window residual
    (8-bit gray levels), applied after the fact (see `track_lk`).
    """

    win_px: int = 5
    max_level: int = 2
    max_iter: int = 10
    eps_px: float = 0.03
    max_error: float = 20.0
    min_eigen: float = 1e-4  # OpenCV's minEigThreshold: weaker windows are not tracked


def track_lk(
    prev_gray: np.ndarray,
    gray: np.ndarray,
    pts_prev: np.ndarray,
    guess: np.ndarray | None,
    lk: LkSettings,
) -> tuple[np.ndarray, np.ndarray]:
    """Move `pts_prev` (N, 2) into `gray`; returns (pts (N, 2) float32, ok (N,)).

    With `guess` the search starts at the predicted positions (Eq. 16, flag
    OPTFLOW_USE_INITIAL_FLOW); without it at the old positions (plain KLT).

    Pyramid: the paper tracks on ORB's 8 levels at scale 1.2, i.e. down to
    1/1.2^7 = 1/3.6 of the image. OpenCV's pyramid halves per level, so
    max_level = 2 (down to 1/4) is the fewest levels that covers that range;
    3 would add a 1/8 level ORB never looked at, with a 5 x 5 window on a
    80 x 60 image.

    Termination (Eq. 20): stop after N_itermax iterations or once converged.
    OpenCV's LK cannot stop on the window residual eps(w) of Eq. 19 itself;
    it stops on the update size (eps_px) instead, and returns eps(w) as its
    `err` output (mean absolute difference over the window, 8-bit units), which
    then rejects points whose window did not match (> max_error).
    """
    p0 = np.ascontiguousarray(pts_prev, dtype=np.float32).reshape(-1, 1, 2)
    if len(p0) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, lk.max_iter, lk.eps_px)
    win = (lk.win_px, lk.win_px)
    if guess is not None:
        p1 = np.array(guess, dtype=np.float32).reshape(-1, 1, 2)  # OpenCV writes into it
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    else:
        p1, flags = p0.copy(), 0
    p1, status, err = cv2.calcOpticalFlowPyrLK(
        prev_gray, gray, p0, p1, winSize=win, maxLevel=lk.max_level, criteria=criteria,
        flags=flags, minEigThreshold=lk.min_eigen,
    )
    pts = p1.reshape(-1, 2)
    h, w = gray.shape
    inside = (pts[:, 0] >= 0) & (pts[:, 0] <= w - 1) & (pts[:, 1] >= 0) & (pts[:, 1] <= h - 1)
    ok = (status.ravel() == 1) & (err.ravel() <= lk.max_error) & inside
    return pts, ok


def gms_inliers(
    p0: np.ndarray,
    p1: np.ndarray,
    size_wh: tuple[int, int],
    grid_cr: tuple[int, int],
    alpha: float,
) -> np.ndarray:
    """Grid-based motion statistics (Bian et al., CVPR 2017) in numpy.

    Motion is smooth: the neighbours of a true match move to the neighbouring
    cells of its target, a false match lands where nobody else goes. For a
    match from cell a to cell b the support S is the number of matches from
    the 3 x 3 cells around a to the same-offset cells around b; it is kept
    when S > alpha * sqrt(n), n the mean number of matches per cell in a's
    neighbourhood (GMS's threshold tau = alpha sqrt(n)). As in GMS, the left
    grid is laid four times, shifted by half a cell, and a match survives if
    one placement keeps it. Unlike GMS, which keeps only the best-supported
    target cell per source cell, each match's own cell pair is scored, so a
    smooth flow split by a cell border keeps both halves.
    """
    n = len(p0)
    if n == 0:
        return np.zeros(0, bool)
    w, h = size_wh
    cols, rows = grid_cr
    cw, ch = w / cols, h / rows
    # Cell indices are offset by one: a zero border around both grids lets the
    # neighbour look-ups run without bounds checks. Left cells without and
    # with the half-cell shift; the counting is compiled (fastorb_kernels).
    bx = np.clip((p1[:, 0] / cw).astype(np.int64), 0, cols - 1) + 1
    by = np.clip((p1[:, 1] / ch).astype(np.int64), 0, rows - 1) + 1
    left_x = np.stack([np.clip(((p0[:, 0] + s * cw) / cw).astype(np.int64), 0, cols - 1 + k) + 1
                       for k, s in enumerate(_HALF_SHIFTS)])
    left_y = np.stack([np.clip(((p0[:, 1] + s * ch) / ch).astype(np.int64), 0, rows - 1 + k) + 1
                       for k, s in enumerate(_HALF_SHIFTS)])
    return gms_keep(left_x, left_y, by * (cols + 2) + bx, cols, rows, (rows + 2) * (cols + 2),
                    alpha)


def epipolar_inliers(
    p0: np.ndarray, p1: np.ndarray, threshold_px: float, confidence: float
) -> np.ndarray:
    """RANSAC on the fundamental matrix (Sec. IV-D): matches within
    `threshold_px` of their epipolar line. Fewer than 8 matches: all kept
    (nothing to test against); a degenerate fit: none kept."""
    n = len(p0)
    if n < 8:
        return np.ones(n, bool)
    _F, mask = cv2.findFundamentalMat(
        np.ascontiguousarray(p0, np.float32), np.ascontiguousarray(p1, np.float32),
        cv2.FM_RANSAC, threshold_px, confidence,
    )
    if mask is None:
        return np.zeros(n, bool)
    return mask.ravel().astype(bool)


def match_by_projection(
    desc: np.ndarray,
    kp_uv: np.ndarray,
    map_desc: np.ndarray,
    map_uv: np.ndarray,
    radius_px: float,
    max_hamming: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Key-frame points projected into the frame at `map_uv` matched to the
    frame's keypoints by descriptor, among the keypoints within `radius_px` of
    the projection (ORB-SLAM's search by projection). Only pairs inside the
    radius are compared, so the cost follows the number of nearby pairs, not
    keypoints x map points (fastorb_kernels.radius_pairs bins the keypoints
    in cells of the radius). Returns index arrays (kp, map), one-to-one, best
    Hamming distance first; equal distances: map points, then keypoints, in
    index order."""
    if len(desc) == 0 or len(map_desc) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    kp_uv = np.ascontiguousarray(kp_uv, np.float64)
    map_uv = np.ascontiguousarray(map_uv, np.float64)
    size = np.maximum(kp_uv.max(axis=0), map_uv.max(axis=0)) + 1.0  # the grid's extent
    q, t, d = radius_pairs(kp_uv, map_uv, float(radius_px), _words(desc), _words(map_desc),
                           int(max_hamming), float(size[0]), float(size[1]))
    best = one_to_one(q, t, d, len(kp_uv), len(map_uv))  # as _unique_pairs does
    return q[best], t[best]


def _words(desc: np.ndarray) -> np.ndarray:
    """(N, 32) uint8 descriptors as (N, 4) uint64 words."""
    return np.ascontiguousarray(desc).view(np.uint64)


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise Hamming distances of binary descriptors (N, 32) uint8."""
    x = np.bitwise_xor(np.ascontiguousarray(a).view(np.uint64), np.ascontiguousarray(b).view(np.uint64))
    return np.bitwise_count(x).sum(axis=1, dtype=np.int64)


def match_by_ratio(
    desc: np.ndarray, map_desc: np.ndarray, ratio: float, max_hamming: int
) -> tuple[np.ndarray, np.ndarray]:
    """Descriptor matches without a pose prior (re-localisation): nearest
    neighbour with Lowe's ratio test, one keypoint per map point."""
    if len(desc) == 0 or len(map_desc) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    knn = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(desc, map_desc, k=2)
    pairs = [m for m in knn if len(m) == 2]
    if not pairs:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    best = np.array([(m[0].queryIdx, m[0].trainIdx, m[0].distance, m[1].distance) for m in pairs])
    ok = (best[:, 2] < ratio * best[:, 3]) & (best[:, 2] <= max_hamming)
    best = best[ok]
    return _unique_pairs(best[:, 0].astype(np.int64), best[:, 1].astype(np.int64), best[:, 2])


def _unique_pairs(
    q: np.ndarray, t: np.ndarray, d: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Greedy one-to-one: pairs by increasing distance, each side used once."""
    order = np.argsort(d, kind="stable")
    q, t = q[order], t[order]
    keep = _first_occurrence(q)
    q, t = q[keep], t[keep]
    keep = _first_occurrence(t)
    return q[keep], t[keep]


def _first_occurrence(a: np.ndarray) -> np.ndarray:
    mask = np.zeros(len(a), bool)
    mask[np.unique(a, return_index=True)[1]] = True
    return mask
