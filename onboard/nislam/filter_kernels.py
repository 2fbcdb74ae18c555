"""Compiled element-wise passes of the correlation filter and its peak
(onboard/nislam/correlation.py): the Gaussian kernel's exponent (Eq. 11),
the whitened gray and the peak lobe's region. numpy took 0.2 ms of passes
over the grid per match for the first two and scipy.ndimage.label 0.25 ms
for the third; these take 0.02 ms and give the same float32 bits
(tests/test_kernels.py), so the tracker's poses do not move. The exp itself
stays with OpenCV, whose SIMD exp a plain loop cannot beat. Cached on disk
and compiled before the first frame as kernels.py's (`warm_up`).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def kernel_exponent(k, sq_sum, scale):
    """In place, k <- max(sq_sum - 2 k, 0) * scale (float32): the Gaussian
    kernel's exponent from the cross term (Eq. 11), one pass instead of
    four numpy passes over the grid, with the same float32 operations in
    the same order (so the same bits); the exp stays with OpenCV."""
    two = np.float32(-2.0)
    for i in range(k.shape[0]):
        for j in range(k.shape[1]):
            v = k[i, j] * two + sq_sum
            if v < np.float32(0.0):  # a NaN stays NaN, as np.maximum keeps it
                v = np.float32(0.0)
            k[i, j] = v * scale
    return k


@njit(cache=True, nogil=True)
def masked_centred(gray, mask, mean):
    """(gray - mean) * mask in float32, one pass and one new array."""
    h, w = gray.shape
    out = np.empty((h, w), np.float32)
    for i in range(h):
        for j in range(w):
            out[i, j] = (gray[i, j] - mean) * mask[i, j]
    return out


@njit(cache=True, nogil=True)
def connected_above(above):
    """0/1 mask of the 4-connected region of `above > 0` that holds the
    window's centre cell (an empty mask when the centre is not above):
    what scipy.ndimage.label's default structure gives, by one flood fill
    from the centre instead of labelling the whole window."""
    h, w = above.shape
    out = np.zeros((h, w), np.uint8)
    ci, cj = h // 2, w // 2
    if not above[ci, cj] > 0.0:
        return out
    stack = np.empty(h * w, np.int64)
    stack[0] = ci * w + cj
    out[ci, cj] = 1
    n = 1
    while n > 0:
        n -= 1
        i, j = divmod(stack[n], w)
        for di, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            a, b = i + di, j + dj
            if 0 <= a < h and 0 <= b < w and out[a, b] == 0 and above[a, b] > 0.0:
                out[a, b] = 1
                stack[n] = a * w + b
                n += 1
    return out


def warm_up() -> None:
    """Compile (or load) each kernel for the types the filter passes."""
    f32 = np.zeros((4, 4), np.float32)
    kernel_exponent(f32.copy(), np.float32(1.0), np.float32(-1.0))
    masked_centred(f32, f32, np.float32(0.0))
    connected_above(np.zeros((5, 5), np.float64))
