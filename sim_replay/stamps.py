"""Capture times of a fixed-rate camera from the host stamps a recording kept.

A recording such as TUM RGB-D stamps each image when the host received it:
the Kinect's frames leave the sensor on a crystal clock (33.3 ms apart), but
their stamps carry the USB and scheduler delay of each transfer, so they
jitter by 1-2 ms RMS (tum_fr1_rpy: intervals alternate 32 and 35 ms; colour
1.5 ms RMS, depth 1.9 ms RMS off a straight line). The replay looks the
attitude up at the frame's stamp, and at fr1/rpy's 65 deg/s median rate 1.5 ms
is 0.1 deg of attitude taken at the wrong time: NI-SLAM turns that into
lateral error in proportion to depth (docs/nislam-error-budget.md), and it
changes from frame to frame. Fitting the stamps to the camera's clock (frame
index -> time, a straight line over a window short enough that the crystals'
relative drift stays linear) gives the capture times back up to a constant
delay, which the AHRS time-offset calibration takes up.

The fit leaves a stream alone where it is not a fixed-rate clock (residuals a
sizeable share of the period): a variable-rate or already exact stream keeps
its stamps.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

DEFAULT_WINDOW_S = 1.0  # +- this around each frame: ~60 stamps at 30 Hz cut 1.5 ms of jitter to 0.2 ms
SEGMENT_GAP_S = 1.0  # a longer step (clock jump, long stall) starts a new clock segment
MIN_SEGMENT_FRAMES = 8  # shorter segments keep their stamps: too few to fit a clock
_MAX_RESIDUAL_SHARE = 0.15  # residual RMS above this share of the period: not a fixed-rate clock
_EXACT_S = 1e-6  # residual RMS below this: the stamps already are the clock (a simulator's), keep them bit-exact
_OUTLIER_MADS = 4.0  # stamps this many robust sigmas off the first fit get no weight in the second


@dataclass(frozen=True)
class StampFit:
    """Fitted capture times and how well the stream followed one clock.

    `t_s` are the capture times (equal to the input where nothing was fitted);
    `period_ms` the median fitted frame period and `residual_rms_ms` the RMS
    of recorded minus fitted stamps over the fitted segments (NaN when none
    was fitted); `frames_fitted` how many stamps were replaced.
    """

    t_s: np.ndarray
    period_ms: float
    residual_rms_ms: float
    frames_fitted: int

    def describe(self) -> str:
        if self.frames_fitted == 0:
            return "stamps as recorded"
        return (f"stamps fitted to a {self.period_ms:.2f} ms clock "
                f"(recorded stamps {self.residual_rms_ms:.2f} ms RMS off it)")


def fit_camera_clock(t_s, window_s: float = DEFAULT_WINDOW_S) -> StampFit:
    """Capture times for increasing stamps `t_s` of a fixed-rate camera.

    Each segment between gaps of SEGMENT_GAP_S is indexed by frame number
    (dropped frames counted from the gap), and each stamp replaced by a
    robust local straight-line fit of time against frame number over
    +-`window_s`. `window_s <= 0` returns the stamps unchanged.
    """
    t = np.asarray(t_s, dtype=np.float64)
    out = t.copy()
    if window_s <= 0 or len(t) < MIN_SEGMENT_FRAMES:
        return StampFit(out, float("nan"), float("nan"), 0)
    periods: list[float] = []
    sq_sum, fitted = 0.0, 0
    cuts = np.flatnonzero(np.diff(t) >= SEGMENT_GAP_S) + 1
    for seg in np.split(np.arange(len(t)), cuts):
        if len(seg) < MIN_SEGMENT_FRAMES:
            continue
        result = _fit_segment(t[seg], window_s)
        if result is None:
            continue
        fit, period_s = result
        out[seg] = fit
        periods.append(period_s * 1e3)
        sq_sum += float(np.sum((t[seg] - fit) ** 2))
        fitted += len(seg)
    if not fitted:
        return StampFit(out, float("nan"), float("nan"), 0)
    return StampFit(out, float(np.median(periods)), float(np.sqrt(sq_sum / fitted)) * 1e3, fitted)


def _fit_segment(t: np.ndarray, window_s: float) -> tuple[np.ndarray, float] | None:
    """(fitted stamps, period [s]) of one gap-free segment, or None if it
    does not follow one fixed-rate clock."""
    period = _frame_period(t)
    if period is None:
        return None
    # Re-index with the line's period: the median interval is biased when the
    # stamps alternate (32/35 ms for a 33.3 ms clock) and long gaps need it exact.
    for _ in range(2):
        index = _frame_index(t, period)
        period = float(np.polyfit(index, t, 1)[0])
    half = max(2, int(round(window_s / period)))
    fit = _local_line(index, t, np.ones_like(t), half)
    resid = t - fit
    sigma = 1.4826 * float(np.median(np.abs(resid - np.median(resid))))
    weights = (np.abs(resid) <= _OUTLIER_MADS * max(sigma, 1e-5)).astype(np.float64)
    fit = _local_line(index, t, weights, half)
    rms = float(np.sqrt(np.mean(((t - fit) * weights) ** 2) * len(t) / max(weights.sum(), 1.0)))
    if rms < _EXACT_S:
        return None
    if rms > _MAX_RESIDUAL_SHARE * period:
        log.debug("stamps %.1f ms RMS off a %.2f ms clock: left as recorded", rms * 1e3, period * 1e3)
        return None
    return fit, period


def _frame_period(t: np.ndarray) -> float | None:
    dt = np.diff(t)
    period = float(np.median(dt))
    return period if period > 0 else None


def _frame_index(t: np.ndarray, period: float) -> np.ndarray:
    """Frame numbers from the stamps: each step counts the frames it spans
    (at least one), so dropped frames keep the clock's count."""
    steps = np.maximum(1.0, np.round(np.diff(t) / period))
    return np.concatenate(([0.0], np.cumsum(steps)))


def _local_line(x: np.ndarray, y: np.ndarray, w: np.ndarray, half: int) -> np.ndarray:
    """Weighted least-squares line through the points with |x - x_j| <= half,
    evaluated at each x_j, in O(n) from cumulative sums. x is centred per
    window to keep the sums well conditioned."""
    x0 = x[0]
    xs = x - x0
    ys = y - y[0]
    lo = np.searchsorted(xs, xs - half, side="left")
    hi = np.searchsorted(xs, xs + half, side="right")

    def window_sum(v: np.ndarray) -> np.ndarray:
        c = np.concatenate(([0.0], np.cumsum(v)))
        return c[hi] - c[lo]

    # Sums about each window's own centre xs_j: sum w (x - c)^k = expand in powers of x.
    c = xs
    s0 = window_sum(w)
    s1 = window_sum(w * xs) - c * s0
    s2 = window_sum(w * xs * xs) - 2 * c * window_sum(w * xs) + c * c * s0
    sy = window_sum(w * ys)
    sxy = window_sum(w * xs * ys) - c * sy
    det = s0 * s2 - s1 * s1
    ok = (s0 >= 2) & (det > 1e-12 * np.maximum(s0 * s2, 1.0))
    intercept = np.where(ok, (s2 * sy - s1 * sxy) / np.where(ok, det, 1.0), ys)
    return intercept + y[0]
