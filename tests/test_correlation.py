"""Kernel correlation filter (NI-SLAM Sec. IV-B/C): shifts, sub-cell peak, PSR.

Conventions under test (onboard/nislam/correlation.py): arrays (H, W) indexed [v, u];
a current image x = np.roll(z, (dv, du), axis=(0, 1)) (content moved right/down)
must give Peak.du_cells = du, Peak.dv_cells = dv.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from onboard.nislam.correlation import KernelCorrelationFilter, find_peak

H, W = 48, 64  # small, non-square grid: rows and columns must not be swapped
SIGMA = 0.2  # authors' kernel sigma
LAM = 0.1  # authors' lambda


def _random_image(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).random((H, W))


def _smooth_image(seed: int, sigma_cells: float = 2.0) -> np.ndarray:
    """Periodic low-pass noise (so a Fourier phase shift is an exact sub-cell
    translation of the same continuous pattern), scaled to [0, 1]."""
    noise = np.random.default_rng(seed).standard_normal((H, W))
    img = gaussian_filter(noise, sigma_cells, mode="wrap")
    return (img - img.min()) / (img.max() - img.min())


def _fourier_shift(img: np.ndarray, du: float, dv: float) -> np.ndarray:
    """Band-limited translation of a periodic image by (du, dv) cells (content
    moves right/down for positive values, like np.roll)."""
    fy = np.fft.fftfreq(img.shape[0])[:, None]
    fx = np.fft.fftfreq(img.shape[1])[None, :]
    return np.real(np.fft.ifft2(np.fft.fft2(img) * np.exp(-2j * np.pi * (fx * du + fy * dv))))


def _trained(z: np.ndarray, label_sigma: float, lam: float = LAM) -> KernelCorrelationFilter:
    f = KernelCorrelationFilter((H, W), SIGMA, lam, label_sigma)
    f.train(z)
    return f


def _reference_response(z, x, sigma, lam, label_sigma, norm="true"):
    """Independent full-spectrum (complex FFT) implementation of Eqs. 10-14.

    norm="true": ||x||^2 (Parseval); norm="half": the authors' sum of |X|^2 / N
    over the r2c half spectrum (reference-nislam.md §5).
    """
    n = z.size

    def sq(a):
        if norm == "true":
            return float(np.sum(a * a))
        return float(np.sum(np.abs(np.fft.rfft2(a)) ** 2) / n)

    def kernel(a, b):
        c = np.real(np.fft.ifft2(np.fft.fft2(a) * np.conj(np.fft.fft2(b))))
        return np.exp(-np.maximum(sq(a) + sq(b) - 2.0 * c, 0.0) / (sigma**2 * n))

    if label_sigma <= 0:
        y = np.zeros(z.shape)
        y[0, 0] = 1.0
    else:
        dv = np.minimum(np.arange(z.shape[0]), z.shape[0] - np.arange(z.shape[0]))
        du = np.minimum(np.arange(z.shape[1]), z.shape[1] - np.arange(z.shape[1]))
        y = np.exp(-0.5 * (dv[:, None] ** 2 + du[None, :] ** 2) / label_sigma**2)
    alpha_hat = np.fft.fft2(y) / (np.fft.fft2(kernel(z, z)) + lam)
    return np.real(np.fft.ifft2(alpha_hat * np.fft.fft2(kernel(x, z))))


# --------------------------------------------------------------- integer shifts
SHIFTS = [
    (0, 0),
    (3, -2),
    (-7, 5),
    (1, 0),
    (0, -1),
    (W // 2 - 1, H // 2 - 1),  # largest positive shifts that are unambiguous
    (-(W // 2 - 1), -(H // 2 - 1)),  # and the most negative ones
    (W // 2 - 1, -(H // 2 - 1)),
]


@pytest.mark.parametrize("label_sigma", [0.0, 1.0])
@pytest.mark.parametrize("du,dv", SHIFTS)
def test_integer_circular_shift_recovered_exactly(label_sigma, du, dv):
    z = _random_image(1)
    f = _trained(z, label_sigma)
    x = np.roll(z, (dv, du), axis=(0, 1))
    peak = find_peak(f.response(x), exclude_half_cells=5)
    # The response of a circularly shifted copy is the training response rolled
    # by (dv, du), and that response is symmetric about 0: the parabola adds
    # nothing, so the shift is exact up to round-off (the filter computes in
    # float32, as the tracker's grids are: measured up to 3e-6 cells).
    assert abs(peak.du_cells - du) < 1e-5
    assert abs(peak.dv_cells - dv) < 1e-5


def test_response_matches_independent_full_spectrum_implementation():
    """Whole response equal to a complex-FFT implementation of Eqs. 10-14 with
    the true norm (pins sign conventions, conjugation, label placement, scale);
    the authors' half-spectrum norm gives a visibly different response."""
    z = _random_image(2)
    x = np.roll(z, (4, -9), axis=(0, 1)) + 0.05 * np.random.default_rng(3).standard_normal((H, W))
    for label_sigma in (0.0, 1.0):
        got = _trained(z, label_sigma).response(x)
        want = _reference_response(z, x, SIGMA, LAM, label_sigma, norm="true")
        # atol: the filter computes in float32 (3.4e-6 measured); peak ~0.85.
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-5)
        half = _reference_response(z, x, SIGMA, LAM, label_sigma, norm="half")
        assert np.max(np.abs(half - want)) > 1e-3


# --------------------------------------------------------------- self response
@pytest.mark.parametrize("label_sigma", [0.0, 1.0])
@pytest.mark.parametrize("lam", [0.1, 1.0])
def test_self_response_peaks_at_zero_with_label_peak_over_one_plus_lambda(label_sigma, lam):
    """Expectation: with the true norm, k_zz(0) = exp(0) = 1 and, for white
    noise, k_zz(s != 0) = exp(-2 (||z||^2 - c(s)) / (sigma^2 N)) ~ exp(-1/(6
    sigma^2)) ~ 0.016 (uniform noise: ||z||^2/N = 1/3, c/N = 1/4), nearly
    constant. So fft(k_zz) ~ 1 at every non-DC frequency and the self response
    r = ifft(y_hat K / (K + lambda)) ~ y / (1 + lambda): the label peak (1)
    scaled by 1/(1 + lambda) -> 0.909 (lambda 0.1), 0.5 (lambda 1).

    Measured 0.9076 / 0.4959 (delta label), 0.9079 / 0.4971 (label sigma 1).
    With the authors' half-spectrum norm (e ~ 0.29 N instead of N/3, same clamp
    of the distance at 0) the off-peak kernel rises to ~exp(-2) and the same
    image gives 0.880 / 0.443: outside the tolerance.
    """
    z = _random_image(4)
    f = _trained(z, label_sigma, lam)
    r = f.response(z)
    v, u = np.unravel_index(int(np.argmax(r)), r.shape)
    assert (v, u) == (0, 0)
    assert r[0, 0] == pytest.approx(1.0 / (1.0 + lam), abs=0.01)
    peak = find_peak(r, 5)
    assert abs(peak.du_cells) < 1e-6 and abs(peak.dv_cells) < 1e-6
    assert peak.value == pytest.approx(r[0, 0])


def test_response_before_training_raises():
    f = KernelCorrelationFilter((H, W), SIGMA, LAM, 0.0)
    assert not f.trained
    with pytest.raises(RuntimeError):
        f.response(_random_image(0))


# --------------------------------------------------------------- sub-cell shift
@pytest.mark.parametrize("label_sigma", [0.0, 1.0])
def test_subcell_shift_recovered_within_a_tenth_of_a_cell(label_sigma):
    """Low-pass noise (Gaussian sigma 2 cells) translated by (2.3, -1.7) cells.
    Measured (seed 5): error ~0.03 cell (delta label), ~0.02 (label sigma 1)."""
    z = _smooth_image(5, 2.0)
    x = _fourier_shift(z, 2.3, -1.7)
    peak = find_peak(_trained(z, label_sigma).response(x), 5)
    assert abs(peak.du_cells - 2.3) < 0.1
    assert abs(peak.dv_cells - (-1.7)) < 0.1


# --------------------------------------------------------------- PSR
@pytest.mark.parametrize("label_sigma", [0.0, 1.0])
def test_psr_high_for_shifted_copy_low_for_unrelated_image(label_sigma):
    """Shifted copy: the response is the (near-delta) training response rolled,
    sidelobes only the regularisation residue; measured PSR ~1e4 (delta label)
    and ~6e3 (label sigma 1); threshold 1000 is 40x the tracker's refine gate.
    Unrelated image: the response is noise-like, so the PSR is the maximum of
    ~N standard normal draws, ~sqrt(2 ln N) ~ 4 for N = 3072 (measured 3.6-4.0;
    max 4.8 over 30 seeds); it must stay below the tracker's psr_lost = 6."""
    z = _random_image(6)
    f = _trained(z, label_sigma)
    shifted = find_peak(f.response(np.roll(z, (-5, 11), axis=(0, 1))), 5)
    unrelated = find_peak(f.response(_random_image(7)), 5)
    assert shifted.psr > 1000.0
    assert unrelated.psr < 6.0
    assert shifted.value > 10 * unrelated.value


def _gaussian_bump(u0: float, v0: float, sigma: float) -> np.ndarray:
    """Circular (wrapped) Gaussian bump centred at (u0, v0) cells."""
    vv, uu = np.mgrid[0:H, 0:W]
    du = (uu - u0 + W / 2) % W - W / 2
    dv = (vv - v0 + H / 2) % H - H / 2
    return np.exp(-(du**2 + dv**2) / (2.0 * sigma**2))


@pytest.mark.parametrize(
    "u0,v0,want_du,want_dv",
    [
        (20.3, 15.8, 20.3, 15.8),
        (-0.4, 0.35, -0.4, 0.35),  # straddles index 0: neighbours wrap around
        (W - 10.45, 7.2, -10.45, 7.2),  # upper half of the range is negative
    ],
)
def test_parabolic_refinement_on_sampled_gaussian(u0, v0, want_du, want_dv):
    """A parabola through three samples of a Gaussian of sigma 2 cells is off
    by < 0.012 cell (computed); a missing/wrong refinement is off by up to 0.5."""
    peak = find_peak(_gaussian_bump(u0, v0, 2.0), 5)
    assert abs(peak.du_cells - want_du) < 0.05
    assert abs(peak.dv_cells - want_dv) < 0.05


def test_parabolic_refinement_exact_on_a_gaussian():
    """A positive peak is fitted on its logarithm, where a sampled Gaussian is
    an exact parabola along each axis."""
    u0, v0 = 30.27, 12.61
    vv, uu = np.mgrid[0:H, 0:W]
    r = 100.0 * np.exp(-((uu - u0) ** 2) / 8.0 - (vv - v0) ** 2 / 4.0)
    peak = find_peak(r, 3)
    assert peak.du_cells == pytest.approx(u0, abs=1e-9)
    assert peak.dv_cells == pytest.approx(v0, abs=1e-9)


def _psr_outside_window(r, v, u, e):
    keep = np.ones(r.shape, bool)
    rows = np.arange(v - e, v + e + 1) % r.shape[0]
    cols = np.arange(u - e, u + e + 1) % r.shape[1]
    keep[np.ix_(rows, cols)] = False
    side = r[keep]
    return (r[v, u] - side.mean()) / side.std()


def test_psr_sidelobe_excludes_window_around_peak():
    """A broad peak (sigma 3 cells) whose skirt reaches past the peak cell: the
    sidelobe statistics over cells outside the (2e+1)^2 window (wrapping at the
    border) give a much higher PSR than the authors' all-cells formula (peak
    zeroed, mean/std over all N cells, ref. §6), whose std is inflated by the
    skirt; exclude_half_cells = 0 is the paper's 'all but the peak cell'."""
    rng = np.random.default_rng(8)
    v0, u0 = 2, W - 3  # window wraps over both borders
    r = _gaussian_bump(u0, v0, 3.0) + 0.01 * rng.standard_normal((H, W))
    r[v0, u0] = 1.5  # unique maximum on the integer grid
    e = 5
    peak = find_peak(r, e)
    assert peak.value == pytest.approx(1.5)
    assert peak.response_sum == pytest.approx(float(r.sum()), rel=1e-12)
    want = _psr_outside_window(r, v0, u0, e)
    assert peak.psr == pytest.approx(want, rel=1e-9)

    zeroed = r.copy()
    zeroed[v0, u0] = 0.0
    psr_all_cells = (1.5 - zeroed.mean()) / zeroed.std()
    assert peak.psr > 3.0 * psr_all_cells  # measured: 91.8 vs 15.9

    peak0 = find_peak(r, 0)
    side = np.delete(r.ravel(), v0 * W + u0)
    assert peak0.psr == pytest.approx((1.5 - side.mean()) / side.std(), rel=1e-9)
    assert peak0.psr < peak.psr


def test_training_into_given_spectra_matches_and_overwrites_them() -> None:
    """A filter handed its spectrum memory (a kept key's slot) trains into it
    and answers exactly as one that allocates; training the next key over the
    same memory replaces the first key's filter completely."""
    z1 = _smooth_image(1).astype(np.float32)
    z2 = _smooth_image(2).astype(np.float32)
    x = _smooth_image(3).astype(np.float32)
    spectra = tuple(np.full((H, W), np.nan, np.float32) for _ in range(2))
    own = KernelCorrelationFilter((H, W), SIGMA, LAM, 1.0, spectra)
    own.train(z1)
    assert np.array_equal(own.response(x), _trained(z1, 1.0).response(x))
    again = KernelCorrelationFilter((H, W), SIGMA, LAM, 1.0, spectra)
    again.train(z2)
    assert np.array_equal(again.response(x), _trained(z2, 1.0).response(x))
    assert np.all(np.isfinite(spectra[0])) and np.all(np.isfinite(spectra[1]))
