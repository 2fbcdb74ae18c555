"""What the data says about the attitude: the residual rotation a frame shows
against its key, and the online attitude time-offset calibration built on it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from onboard.core.messages import AttitudeSource
from onboard.core.rotations import so3_log
from onboard.nislam import kernels as kern
from onboard.nislam.params import NislamParams
from onboard.nislam.projection import AxonometricImage


@dataclass
class RotationResidual:
    """The key image kept to measure the residual rotation of later frames.

    A residual rotation theta shifts content by theta x p, i.e. in proportion
    to depth, while a translation shifts every depth alike. One linearised
    least-squares step over n x n blocks fits both at once: the block shift
    d0 + r (z - z_mean), whose depth rate r is theta as the colour image sees
    it. That is what the attitude time offset must be calibrated against (the
    depth image of a Kinect-class sensor is captured at another instant, so
    the tilt of the depth differences calibrates the wrong clock).

    Only blocks covered in both images whose depths agree take part: where
    near objects hide the far surfaces depends on where the camera stands,
    and a correlation over whole layers was pulled by those moving hole
    outlines (a 20-26 ms offset bias on a synthetic orbit with exact attitude,
    none on a pure yaw spin). The blocks' own depths set the depth rate, so no
    layer means enter it.
    """

    gray: np.ndarray  # the key's gray, depth and mask at full resolution
    depth_m: np.ndarray
    mask: np.ndarray

    @classmethod
    def train(cls, img: AxonometricImage, p: "NislamParams") -> "RotationResidual | None":
        depths = img.depth_m[img.mask > 0]
        # Without depth relief a rotation cannot be told from a translation.
        if len(depths) < 100 or float(np.std(depths)) < 0.5 * p.layer_min_gap_m:
            return None
        return cls(img.gray, img.depth_m, img.mask)

    def residual(
        self,
        img: AxonometricImage,
        shift_cells: tuple[float, float],
        tz_m: float,
        p: "NislamParams",
    ) -> np.ndarray | None:
        """theta (x, y, 0) in key axes [rad], or None when the fit is not
        determined. The frame's depths are the key's minus t_z."""
        n = p.layer_downsample
        du, dv = int(round(shift_cells[0])), int(round(shift_cells[1]))
        ks, cs = overlap(img.gray.shape, du, dv)
        if ks is None:
            return None
        # Coverage per block, not per cell, decides what both images hold: two
        # sparse samplings of one surface share few cells but the same blocks.
        key_g, key_z, key_cover = kern.block_means(self.gray[ks], self.depth_m[ks], self.mask[ks], n)
        cur_g, cur_z, cur_cover = kern.block_means(img.gray[cs], img.depth_m[cs], img.mask[cs], n)
        ok = (key_cover >= p.layer_min_cover) & (cur_cover >= p.layer_min_cover)
        ok &= np.abs(cur_z + tz_m - key_z) < p.gate_depth_m
        inner = ok[1:-1, 1:-1] & ok[1:-1, 2:] & ok[1:-1, :-2] & ok[2:, 1:-1] & ok[:-2, 1:-1]
        if inner.sum() < 100:
            return None
        # Mean of both images' central differences: second-order accurate.
        gx = 0.25 * (key_g[1:-1, 2:] - key_g[1:-1, :-2] + cur_g[1:-1, 2:] - cur_g[1:-1, :-2])[inner]
        gy = 0.25 * (key_g[2:, 1:-1] - key_g[:-2, 1:-1] + cur_g[2:, 1:-1] - cur_g[:-2, 1:-1])[inner]
        err = (cur_g[1:-1, 1:-1] - key_g[1:-1, 1:-1])[inner]
        err = err - err.mean()  # an exposure change is not a shift
        z = key_z[1:-1, 1:-1][inner]
        z = z - z.mean()
        if float(np.std(z)) < 0.5 * p.layer_min_gap_m:
            return None
        # cur(q) = key(q - d(q)), d = d0 + r z  =>  err ~ -grad . (d0 + r z).
        a = np.stack([gx, gy, gx * z, gy * z], axis=1).astype(np.float64)
        ata = a.T @ a
        if np.linalg.eigvalsh(ata)[0] < 1e-9 * len(z):
            return None
        _, _, ru, rv = -np.linalg.solve(ata, a.T @ err.astype(np.float64))
        # d s = -(t + theta x p) in cells of res: du grows by -theta_y z,
        # dv by +theta_x z; r is in blocks of n cells per metre.
        s = img.res_m * n
        return np.array([rv * s, -ru * s, 0.0])


@dataclass
class OffsetCalibration:
    """Online least squares for the attitude time offset.

    A time error eps makes the residual rotation theta ~ eps * g, with g the
    difference of the key's and the current frame's angular rates in key axes.
    Each frame implies offset_true ~ offset_used - (g . theta) / |g|^2; the
    estimate is the |g|^2-weighted mean of those with exponential forgetting.
    """

    forget: float
    max_s: float
    offset_s: float
    num: float = 0.0
    den: float = 0.0
    n: int = 0

    MIN_G2 = 0.05  # |g|^2 [rad^2/s^2]: below ~13 deg/s the residual says nothing about time

    def informative(self, g_rad_s: np.ndarray) -> bool:
        """Whether `update` would use a frame with rate difference `g_rad_s`
        (a caller need not measure the residual when not)."""
        return float(g_rad_s @ g_rad_s) >= self.MIN_G2

    def update(self, g_rad_s: np.ndarray, theta_rad: np.ndarray) -> None:
        g2 = float(g_rad_s @ g_rad_s)
        if g2 < self.MIN_G2:
            return
        self.num = self.forget * self.num + g2 * self.offset_s - float(g_rad_s @ theta_rad)
        self.den = self.forget * self.den + g2
        self.n += 1
        if self.n >= 20:
            self.offset_s = float(np.clip(self.num / self.den, -self.max_s, self.max_s))


def overlap(shape: tuple[int, int], du: int, dv: int):
    """Slices (key, current) with current[p + d] aligned to key[p]: a zero-filled,
    non-circular shift (ref. pitfalls: np.roll is wrong here)."""
    h, w = shape
    if abs(du) >= w or abs(dv) >= h:
        return None, None
    ky = slice(max(0, -dv), min(h, h - dv))
    kx = slice(max(0, -du), min(w, w - du))
    cy = slice(ky.start + dv, ky.stop + dv)
    cx = slice(kx.start + du, kx.stop + du)
    return (ky, kx), (cy, cx)


def body_rate(attitude: AttitudeSource, t_s: float, half_s: float) -> np.ndarray | None:
    """Angular rate in the camera frame from two attitude look-ups (rad/s)."""
    r0 = attitude.rotation_at(t_s - half_s)
    r1 = attitude.rotation_at(t_s + half_s)
    if r0 is None or r1 is None:
        return None
    return so3_log(r0.T @ r1) / (2.0 * half_s)
