"""Sensor models of the synthetic flights: camera mounts, an RGB-D depth
sensor (noise, holes, range), colour noise, and the AHRS (rate, error model,
dropouts, named profiles).

Pure functions of their inputs and a numpy Generator: the same seed gives the
same errors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from onboard import NislamError
from sim_replay.attitude import AttitudeErrorModel, perturb_samples

# --------------------------------------------------------------------------- mounts


# --------------------------------------------------------------------------- depth


@dataclass(frozen=True)
class DepthSensorModel:
    """A stereo / structured-light depth camera.

    sigma_m_per_m2: depth noise std = sigma_m_per_m2 * z^2 (disparity noise
        maps to depth as z^2 / (f B); 0.0015 is ~1.5 mm at 1 m, 2.4 cm at 4 m,
        Kinect/RealSense class).
    min_range_m / max_range_m: no depth outside (true depth).
    edge_rel: a pixel whose 3x3 neighbourhood spans more than edge_rel * z is on
        a depth edge and invalid (matching windows straddle the edge there);
        edge_width_px more pixels around it are invalid too.
    dropout: share of further random invalid pixels (specular, dark spots).
    """

    sigma_m_per_m2: float = 0.0015
    min_range_m: float = 0.3
    max_range_m: float = 6.0
    edge_rel: float = 0.04
    edge_width_px: int = 1
    dropout: float = 0.0

    def __post_init__(self) -> None:
        if self.sigma_m_per_m2 < 0 or not 0 <= self.dropout < 1 or self.edge_width_px < 0:
            raise NislamError("depth model: sigma >= 0, 0 <= dropout < 1, edge width >= 0")
        if not 0 <= self.min_range_m < self.max_range_m:
            raise NislamError("depth model: need 0 <= min_range_m < max_range_m")


PERFECT_DEPTH = DepthSensorModel(sigma_m_per_m2=0.0, min_range_m=0.0, max_range_m=1e9,
                                 edge_rel=math.inf, edge_width_px=0)


def measure_depth(depth_m: np.ndarray, model: DepthSensorModel, rng: np.random.Generator
                  ) -> np.ndarray:
    """The sensor's depth (float32, 0 = invalid) for true depth `depth_m`.

    The noise is drawn per 2x2 pixel block: a stereo matcher's window makes
    neighbouring disparities err together, and a quarter of the draws keeps
    the sensor model at a few milliseconds a frame.
    """
    z = depth_m.astype(np.float32, copy=False)
    h, w = z.shape
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
    out = z.copy()
    if model.sigma_m_per_m2 > 0:
        blocks = rng.standard_normal(((h + 1) // 2, (w + 1) // 2), dtype=np.float32)
        noise = cv2.resize(blocks, (2 * blocks.shape[1], 2 * blocks.shape[0]),
                           interpolation=cv2.INTER_NEAREST)[:h, :w]
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
    try:
        return dict(AHRS_PROFILES[name])
    except KeyError:
        raise NislamError(
            f"unknown AHRS profile {name!r} (known: {', '.join(AHRS_PROFILES)})"
        ) from None


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
