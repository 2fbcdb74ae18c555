"""Sensor models of the synthetic flights: camera mounts, an RGB-D depth
sensor (noise, holes, range), colour noise, and the AHRS (rate, error model,
dropouts, named profiles).

Pure functions of their inputs and a numpy Generator: the same seed gives the
same errors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypeVar

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from onboard import NislamError
from sim_replay.attitude import AttitudeErrorModel, perturb_samples

T = TypeVar("T")

# --------------------------------------------------------------------------- mounts


# --------------------------------------------------------------------------- depth


@dataclass(frozen=True)
class DisparityModel:
    """How a stereo or structured-light sensor errs: in disparity, not in depth.

    Depth is z = f B / d. The matcher finds d by correlating a window of
    `window_px` x `window_px` pixels, so the disparities of pixels closer than a
    window err together (patches, not independent pixels), and it reports d
    in steps of `subpixel_px` (Kinect v1: 1/8 px), so the depth comes in steps
    of z^2 / (f B) * subpixel_px that grow with the square of the distance
    (Khoshelham & Elberink 2012, Eq. 9; Smisek et al. 2011).
    focal_px / baseline_m: of the matching (IR) camera, not the colour one.
    sigma_px: disparity noise std before the rounding to steps.
    """

    focal_px: float = 580.0
    baseline_m: float = 0.075
    subpixel_px: float = 0.125
    sigma_px: float = 0.075
    window_px: int = 9

    def __post_init__(self) -> None:
        if self.focal_px <= 0 or self.baseline_m <= 0 or self.subpixel_px <= 0:
            raise NislamError("disparity model: focal, baseline and subpixel step must be > 0")
        if self.sigma_px < 0 or self.window_px < 1:
            raise NislamError("disparity model: sigma >= 0, window >= 1 px")

    def depth_step_m(self, z_m: float | np.ndarray) -> float | np.ndarray:
        """Depth between two neighbouring disparity steps at depth z."""
        return np.asarray(z_m) ** 2 * (self.subpixel_px / (self.focal_px * self.baseline_m))


# Kinect v1 (TUM RGB-D): IR camera f ~580 px, projector-camera baseline 7.5 cm,
# disparity in 1/8 px (11-bit raw), 9x9 correlation window. sigma_px: Nguyen et
# al. 2012 measure sigma_z ~ 0.0019 z^2 m far out, i.e. 0.083 px of disparity
# in all, of which the rounding to 1/8 px is 0.125 / sqrt(12) = 0.036 px.
KINECT_V1 = DisparityModel()


@dataclass(frozen=True)
class DepthSensorModel:
    """A stereo / structured-light depth camera.

    sigma_m_per_m2: depth noise std = sigma_m_per_m2 * z^2 (disparity noise
        maps to depth as z^2 / (f B); 0.0015 is ~1.5 mm at 1 m, 2.4 cm at 4 m,
        Kinect/RealSense class), drawn per 2x2 pixel block and not quantised.
    min_range_m / max_range_m: no depth outside (true depth).
    edge_rel: a pixel whose 3x3 neighbourhood spans more than edge_rel * z is on
        a depth edge and invalid (matching windows straddle the edge there);
        edge_width_px more pixels around it are invalid too.
    dropout: share of further random invalid pixels (specular, dark spots).
    disparity: if set, the noise is that sensor's disparity error (window-
        correlated, rounded to disparity steps) and sigma_m_per_m2 is unused.
    """

    sigma_m_per_m2: float = 0.0015
    min_range_m: float = 0.3
    max_range_m: float = 6.0
    edge_rel: float = 0.04
    edge_width_px: int = 1
    dropout: float = 0.0
    disparity: DisparityModel | None = None

    def __post_init__(self) -> None:
        if self.sigma_m_per_m2 < 0 or not 0 <= self.dropout < 1 or self.edge_width_px < 0:
            raise NislamError("depth model: sigma >= 0, 0 <= dropout < 1, edge width >= 0")
        if not 0 <= self.min_range_m < self.max_range_m:
            raise NislamError("depth model: need 0 <= min_range_m < max_range_m")


PERFECT_DEPTH = DepthSensorModel(sigma_m_per_m2=0.0, min_range_m=0.0, max_range_m=1e9,
                                 edge_rel=math.inf, edge_width_px=0)

# Named depth profiles (`nislam sim --depth-profile`): "gaussian" is the model
# the flights were rendered with so far, "kinect" a Kinect v1 as in TUM RGB-D.
DEPTH_PROFILES: dict[str, DepthSensorModel] = {
    "gaussian": DepthSensorModel(),
    "kinect": DepthSensorModel(disparity=KINECT_V1),
}


def _named(table: dict[str, T], kind: str, name: str) -> T:
    """The entry `name` of a table of named profiles; one line naming the known ones if absent."""
    try:
        return table[name]
    except KeyError:
        raise NislamError(f"unknown {kind} {name!r} (known: {', '.join(table)})") from None


def depth_profile(name: str) -> DepthSensorModel:
    return _named(DEPTH_PROFILES, "depth profile", name)


def _block_normals(shape_hw: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """Standard normals drawn per 2x2 pixel block, at full resolution."""
    h, w = shape_hw
    blocks = rng.standard_normal(((h + 1) // 2, (w + 1) // 2), dtype=np.float32)
    return cv2.resize(blocks, (2 * blocks.shape[1], 2 * blocks.shape[0]),
                      interpolation=cv2.INTER_NEAREST)[:h, :w]


def _window_gain(window_px: int) -> float:
    """Std of a window_px-wide box mean of 2x2-block normals (averaged over the
    window's two phases against the blocks, per axis)."""
    v = [np.sum((np.bincount((np.arange(window_px) + p) // 2) / window_px) ** 2) for p in (0, 1)]
    return float(np.mean(v))  # sqrt of the 2-D variance, the product of two equal 1-D ones


def _disparity_depth(z: np.ndarray, disp: DisparityModel, rng: np.random.Generator
                     ) -> np.ndarray:
    """Depth through a disparity matcher: noise correlated over the matching
    window (the box mean of the same per-block draws), then rounded to whole
    disparity steps; 0 where the disparity rounds to 0 or below."""
    fb = np.float32(disp.focal_px * disp.baseline_m)
    step = np.float32(disp.subpixel_px)
    d = np.where(z > 0, fb / np.maximum(z, np.float32(1e-6)), np.float32(0))
    if disp.sigma_px > 0:
        k = disp.window_px
        noise = cv2.blur(_block_normals(z.shape, rng), (k, k), borderType=cv2.BORDER_REFLECT)
        d += noise * np.float32(disp.sigma_px / _window_gain(k))
    dq = np.rint(d / step) * step
    return np.where(dq > 0, fb / np.maximum(dq, step), np.float32(0)).astype(np.float32)


def measure_depth(depth_m: np.ndarray, model: DepthSensorModel, rng: np.random.Generator
                  ) -> np.ndarray:
    """The sensor's depth (float32, 0 = invalid) for true depth `depth_m`.

    Gaussian model: the noise is drawn per 2x2 pixel block (a quarter of the
    draws keeps the sensor model at a few milliseconds a frame). Disparity
    model: the same draws, averaged over the matching window and rounded to
    disparity steps (`_disparity_depth`); both consume the generator alike, so
    a flight's colour noise does not depend on the depth profile.
    """
    z = depth_m.astype(np.float32, copy=False)
    valid = (z > model.min_range_m) & (z < model.max_range_m)
    if math.isfinite(model.edge_rel):
        kernel = np.ones((3, 3), np.uint8)
        span = cv2.dilate(z, kernel) - cv2.erode(z, kernel)
        edge = (span > np.float32(model.edge_rel) * z).astype(np.uint8)
        if model.edge_width_px > 0:
            k = 2 * model.edge_width_px + 1
            edge = cv2.dilate(edge, np.ones((k, k), np.uint8))
        valid &= edge == 0
    if model.dropout > 0:
        valid &= rng.random(z.shape, dtype=np.float32) >= model.dropout
    if model.disparity is not None:
        out = _disparity_depth(z, model.disparity, rng)
    else:
        out = z.copy()
        if model.sigma_m_per_m2 > 0:
            noise = _block_normals(z.shape, rng)
            out += noise * (np.float32(model.sigma_m_per_m2) * z * z)
    out *= valid
    np.maximum(out, 0.0, out=out)  # a noisy depth below zero is no depth
    return out


def depth_to_png_units(depth_m: np.ndarray, depth_scale: float) -> np.ndarray:
    """uint16 depth image (0 = invalid); values beyond the 16-bit range are invalid."""
    units = depth_m.astype(np.float32) * np.float32(depth_scale) + np.float32(0.5)  # round
    units[(units >= 65536.0) | ~(units >= 0.0)] = 0.0
    return units.astype(np.uint16)


# --------------------------------------------------------------------------- colour


class ColourNoise:
    """Additive Gaussian pixel noise of `sigma_dn` grey levels.

    Drawing 0.9 million normals per frame would cost more than rendering, so a
    few noise images are drawn once and each frame takes one at a random
    offset (deterministic for the seed); saturating uint8 arithmetic.
    """

    def __init__(self, shape_hw: tuple[int, int], sigma_dn: float, seed: int, bank: int = 4,
                 pad: int = 32) -> None:
        self.sigma_dn = float(sigma_dn)
        self.pad = pad
        self._pos: list[np.ndarray] = []
        self._neg: list[np.ndarray] = []
        if self.sigma_dn <= 0:
            return
        rng = np.random.default_rng([seed, 0xC0])
        h, w = shape_hw
        for _ in range(bank):
            n = np.rint(rng.standard_normal((h + pad, w + pad, 3)) * self.sigma_dn)
            self._pos.append(np.clip(n, 0, 255).astype(np.uint8))
            self._neg.append(np.clip(-n, 0, 255).astype(np.uint8))

    def apply(self, bgr: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        if not self._pos:
            return bgr
        h, w = bgr.shape[:2]
        k = int(rng.integers(len(self._pos)))
        dy, dx = (int(v) for v in rng.integers(0, self.pad + 1, 2))
        out = cv2.add(bgr, self._pos[k][dy:dy + h, dx:dx + w])
        return cv2.subtract(out, self._neg[k][dy:dy + h, dx:dx + w])


# --------------------------------------------------------------------------- AHRS


@dataclass(frozen=True)
class AhrsModel:
    """The attitude sensor: sample rate, error model (see AttitudeErrorModel;
    errors act in the body frame) and a share of samples lost (dropout)."""

    rate_hz: float = 100.0
    errors: AttitudeErrorModel = AttitudeErrorModel()
    dropout: float = 0.0

    def __post_init__(self) -> None:
        if not 0 < self.rate_hz <= 1000:  # beyond any AHRS; a typo, not a sensor
            raise NislamError(f"AHRS rate must be in (0, 1000] Hz, got {self.rate_hz:g}")
        if not 0 <= self.dropout < 1:
            raise NislamError(f"AHRS dropout must be in [0, 1), got {self.dropout}")


# Named profiles: typical figures for the sensor class, not a calibration of one
# unit (the myAHRS+ publishes no noise density; these are what a consumer
# MEMS AHRS with a Kalman filter delivers at rest and in slow flight).
AHRS_PROFILES: dict[str, dict[str, float]] = {
    "perfect": {"noise_deg": 0.0, "bias_deg_per_sqrt_s": 0.0, "offset_ms": 0.0, "dropout": 0.0},
    # myAHRS+ over USB: ~0.1 deg jitter, slow drift, a few ms of USB/serial
    # latency, an occasional lost line at 100 Hz.
    "myahrs": {"noise_deg": 0.1, "bias_deg_per_sqrt_s": 0.02, "offset_ms": 5.0,
               "dropout": 0.005},
    # An autopilot's EKF attitude over MAVLink telemetry: smoother, later.
    "autopilot": {"noise_deg": 0.05, "bias_deg_per_sqrt_s": 0.01, "offset_ms": 20.0,
                  "dropout": 0.01},
}


def ahrs_profile(name: str) -> dict[str, float]:
    return dict(_named(AHRS_PROFILES, "AHRS profile", name))


AHRS_MARGIN_S = 0.15  # attitude before the first / after the last frame: a replay
# that shifts the attitude clock (error model offset, online calibration up to
# 0.1 s) still finds attitude for every frame


def ahrs_sample_times(t_first_s: float, t_last_s: float, rate_hz: float, phase_s: float,
                      margin_s: float = AHRS_MARGIN_S) -> np.ndarray:
    """Stamps of an AHRS running on its own clock (phase `phase_s`), covering
    [t_first - margin, t_last + margin]; rounded to microseconds as written."""
    dt = 1.0 / rate_hz
    start = t_first_s - margin_s + phase_s % dt
    n = int(math.floor((t_last_s + margin_s - start) / dt)) + 1
    return np.round(start + dt * np.arange(n), 6)


def measure_attitude(t_s: np.ndarray, true_R_W_B_at, model: AhrsModel,
                     rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(stamps, q_W_B_xyzw) the AHRS reports at `t_s`.

    `true_R_W_B_at(t)` gives the true body orientation (N, 3, 3); the sample
    stamped t holds the truth at t - offset, then bias and noise
    (sim_replay.attitude.perturb_samples); dropped samples are left out
    after the errors are drawn, so a dropout does not change the others.
    """
    t = np.asarray(t_s, dtype=np.float64)
    r_true = true_R_W_B_at(t - model.errors.offset_ms * 1e-3)
    q_true = Rotation.from_matrix(r_true).as_quat()
    q_meas = perturb_samples(t, q_true, model.errors)
    keep = np.ones(len(t), dtype=bool)
    if model.dropout > 0:
        keep = rng.random(len(t)) >= model.dropout
    return t[keep], q_meas[keep]
