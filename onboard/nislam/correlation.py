"""Gaussian-kernel correlation filter in the Fourier domain (NI-SLAM Sec. IV-B).

The key axonometric gray image z is learned once per key frame (Eq. 12); every
frame then gets the response over all circular shifts in one shot (Eq. 14), its
peak (Eq. 15) and the peak-to-sidelobe ratio (Eq. 16). Arrays are (H, W) = (rows,
cols) indexed [v, u]; shifts are (du, dv) in cells, positive = content moved
right/down in the current image relative to the key.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from onboard.nislam.filter_kernels import connected_above, kernel_exponent, masked_centred

# The filter's transforms are OpenCV's real DFT and its spectrum products, in
# OpenCV's packed layout (CCS: a real (H, W) array). At 480 x 360 float32 they
# take 0.53 / 0.70 ms forward / inverse against scipy.fft's 0.67 / 0.84, and
# cv2.exp 0.07 ms against numpy's 0.37 (this machine, one thread; a match has
# four transforms and one exp). OpenCV keeps them on the calling thread unless
# its own pool is enabled (`nislam bench` pins it to one thread).
_INVERSE_REAL = cv2.DFT_INVERSE | cv2.DFT_REAL_OUTPUT | cv2.DFT_SCALE
# Half size of the window the lobe centroid looks in: on tum_fr1_rpy the lobe
# above half height reaches up to ~10 cells from the peak (32 cells median, 102-138
# max), elongated along the image flow; a lobe cut by the window is biased
# toward the arg-max.
_LOBE_HALF_CELLS = 12


@dataclass(frozen=True)
class Peak:
    """Response peak: sub-cell shift, raw peak value and PSR (Eq. 16)."""

    du_cells: float
    dv_cells: float
    value: float
    psr: float
    response_sum: float


def dft(a: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Real 2-D DFT of `a` in float32, CCS-packed (the same shape)."""
    return cv2.dft(np.asarray(a, np.float32), dst=out)


def idft_real(spectrum: np.ndarray) -> np.ndarray:
    """Inverse of `dft`, scaled by 1/N: the real array back."""
    return cv2.dft(spectrum, flags=_INVERSE_REAL)


@lru_cache(maxsize=4)
def gaussian_label_spectrum(shape: tuple[int, int], sigma_cells: float) -> np.ndarray:
    """DFT of the regression target y (Eq. 3): a delta at shift 0 as in the
    paper when sigma is 0, else a narrow circular Gaussian centred at shift 0.

    The label sits at index (0, 0) rather than the image centre so the response
    peak index *is* the shift (mod size): no fftshift per frame. One read-only
    array per (shape, sigma), shared by every filter: a kept key would
    otherwise hold its own copy (0.7 MB at 480 x 360).
    """
    h, w = shape
    if sigma_cells <= 0.0:
        y = np.zeros(shape, np.float32)
        y[0, 0] = 1.0
    else:
        dv = np.minimum(np.arange(h), h - np.arange(h)).astype(np.float32)
        du = np.minimum(np.arange(w), w - np.arange(w)).astype(np.float32)
        y = np.exp(-0.5 * (dv[:, None] ** 2 + du[None, :] ** 2) / sigma_cells**2).astype(np.float32)
    y_hat = dft(y)
    y_hat.setflags(write=False)
    return y_hat


class KernelCorrelationFilter:
    """Gaussian-kernel ridge regression over all circular shifts (Eqs. 10-14).

    The kernel uses the true squared norms ||x||^2 (Parseval), so k <= 1 and
    lambda keeps its textbook meaning; the authors' half-spectrum sum instead
    scales k by a constant factor and with it the effective lambda.
    """

    def __init__(
        self, shape: tuple[int, int], sigma: float, lam: float, label_sigma_cells: float,
        spectra: tuple[np.ndarray, np.ndarray] | None = None,
    ):
        """`spectra`: two float32 (H, W) arrays (CCS) that `train`
        fills with z_hat and alpha_hat instead of allocating them (a tracker
        that keeps key frames owns their memory up front)."""
        self.shape = shape
        self.n_cells = shape[0] * shape[1]
        self.sigma = sigma
        self.lam = lam
        self._label_hat = gaussian_label_spectrum(shape, label_sigma_cells)
        self._spectra = spectra
        self._z_hat: np.ndarray | None = None
        self._z_sq = 0.0
        self._alpha_hat: np.ndarray | None = None

    @property
    def trained(self) -> bool:
        return self._alpha_hat is not None

    def _kernel(self, x_hat: np.ndarray, x_sq: float) -> np.ndarray:
        """k^{xz} over all shifts: exp(-||x - shift(z)||^2 / (sigma^2 N)) (Eq. 11),
        with the cross term from one inverse DFT (circulant trick, Lemma 1)."""
        k = idft_real(cv2.mulSpectrums(x_hat, self._z_hat, 0, conjB=True))
        # In place and in one pass: this runs on every frame over the whole
        # grid, where numpy's four passes cost more than the arithmetic.
        kernel_exponent(k, np.float32(x_sq + self._z_sq),
                        np.float32(-1.0 / (self.sigma**2 * self.n_cells)))
        return cv2.exp(k, dst=k)

    def train(self, z: np.ndarray) -> None:
        """Learn alpha for key image z (Eq. 12): alpha_hat = y_hat / (k_hat^{zz} + lambda)."""
        z_out, alpha_out = self._spectra if self._spectra is not None else (None, None)
        self._z_hat = dft(z, z_out)
        self._z_sq = float(np.vdot(z, z))  # z as given: its norm in its own precision
        k = self._kernel(self._z_hat, self._z_sq)
        k[0, 0] += np.float32(self.lam)  # + lambda on every frequency: a delta of lambda at shift 0
        self._alpha_hat = cv2.divSpectrums(self._label_hat, dft(k), 0, c=alpha_out)

    def response(self, x: np.ndarray) -> np.ndarray:
        """Response over all circular shifts of x (Eq. 14)."""
        if self._alpha_hat is None:
            raise RuntimeError("filter used before train()")
        k_hat = dft(self._kernel(dft(x), float(np.vdot(x, x))))
        return idft_real(cv2.mulSpectrums(k_hat, self._alpha_hat, 0))


def find_peak(
    response: np.ndarray,
    exclude_half_cells: int,
    centre_cells: tuple[float, float] = (0.0, 0.0),
    radius_cells: int | None = None,
    lobe_centroid: bool = False,
) -> Peak:
    """Arg-max refined to sub-cell by a parabola through the peak and its
    circular neighbours on each axis, or (`lobe_centroid`) by the centroid of
    the peak's lobe above half its height; PSR (Eq. 16) over the sidelobe,
    i.e. all cells outside a (2e+1)^2 window around the peak, so the peak's
    own skirt does not deflate the ratio.

    Eq. 15 takes the peak's whole cell. The parabola through three samples
    is exact for a Gaussian lobe; on real images the lobe is neither
    Gaussian nor narrow (tum_fr1_rpy: half height 2-3 cells from the peak,
    log-linear skirts, stretched along the flow by motion blur and the
    rolling shutter), and the three top samples differ by less than their
    noise. The centroid of the connected lobe above half height is unbiased
    for any lobe symmetric about the true shift, whatever its shape, and
    averages ~30 cells instead of 3 (docs/nislam-error-budget.md, "The
    correlation peak").

    With `radius_cells`, the arg-max is searched only within that many cells
    of `centre_cells` (du, dv): a motion prior that keeps a distant look-alike
    of the scene (repeated texture) from winning.
    """
    h, w = response.shape
    if radius_cells is None or 2 * radius_cells + 1 >= min(h, w):
        v, u = divmod(int(np.argmax(response)), w)
    else:
        cu, cv = int(round(centre_cells[0])), int(round(centre_cells[1]))
        rows = np.arange(cv - radius_cells, cv + radius_cells + 1) % h
        cols = np.arange(cu - radius_cells, cu + radius_cells + 1) % w
        i, j = divmod(int(np.argmax(response[np.ix_(rows, cols)])), len(cols))
        v, u = int(rows[i]), int(cols[j])
    r_max = float(response[v, u])
    centroid = _lobe_centroid(response, v, u, r_max) if lobe_centroid else None
    if centroid is not None:
        du, dv = centroid
    else:
        dv = _parabolic_offset(response[(v - 1) % h, u], r_max, response[(v + 1) % h, u])
        du = _parabolic_offset(response[v, (u - 1) % w], r_max, response[v, (u + 1) % w])
    # Circular shift range is +-size/2 (reference-nislam.md, pitfalls).
    shift_v = v + dv if v <= h // 2 else v + dv - h
    shift_u = u + du if u <= w // 2 else u + du - w
    psr, total = _psr(response, v, u, r_max, exclude_half_cells)
    return Peak(float(shift_u), float(shift_v), r_max, psr, total)


def _lobe_centroid(r: np.ndarray, v: int, u: int, r_max: float) -> tuple[float, float] | None:
    """(du, dv) of the centroid of the connected region around (v, u) where
    the response exceeds half the peak, each cell weighted by its height
    above half (zero at the region's edge, so cells entering or leaving it
    do not jump the centroid); None without a positive peak."""
    if not r_max > 0.0:
        return None
    h, w = r.shape
    e = min(_LOBE_HALF_CELLS, (min(h, w) - 1) // 2)
    rows = np.arange(v - e, v + e + 1) % h
    cols = np.arange(u - e, u + e + 1) % w
    above = r[np.ix_(rows, cols)].astype(np.float64) - 0.5 * r_max
    weight = np.where(connected_above(above) == 1, above, 0.0)
    total = float(weight.sum())
    if not total > 0.0:
        return None
    offsets = np.arange(-e, e + 1, dtype=np.float64)
    return float(weight.sum(axis=0) @ offsets) / total, float(weight.sum(axis=1) @ offsets) / total


def _parabolic_offset(left: float, centre: float, right: float) -> float:
    """Vertex of the parabola through three samples; on the logarithms when
    all are positive (exact for a Gaussian peak, which a narrow Gaussian label
    gives), which removes most of the pull toward whole cells."""
    if left > 0.0 and right > 0.0 and centre > 0.0:
        left, centre, right = np.log(left), np.log(centre), np.log(right)
    denom = left - 2.0 * centre + right
    if denom >= 0.0:  # not a strict maximum: no refinement
        return 0.0
    return float(np.clip(0.5 * (left - right) / denom, -0.5, 0.5))


def _psr(r: np.ndarray, v: int, u: int, r_max: float, e: int) -> tuple[float, float]:
    h, w = r.shape
    rows = np.arange(v - e, v + e + 1) % h
    cols = np.arange(u - e, u + e + 1) % w
    win = r[np.ix_(rows, cols)]
    total = float(r.sum())  # numpy's pairwise float32 sum: ~1e-7 relative, no float64 copy
    total_sq = float(np.vdot(r, r))
    n_side = r.size - win.size
    mean = (total - float(win.sum())) / n_side
    var = (total_sq - float(np.vdot(win, win))) / n_side - mean * mean
    if not np.isfinite(var) or var <= 0.0:
        return 0.0, total
    return (r_max - mean) / np.sqrt(var), total


def whiten(gray: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Zero-mean gray over filled cells, holes at 0: holes then carry no
    pattern of their own (the authors fill them with 0.5, which correlates the
    hole layout of the two images)."""
    n = float(mask.sum())
    mean = float(np.vdot(gray, mask)) / n if n > 0 else 0.0
    return masked_centred(gray, mask, np.float32(mean))
