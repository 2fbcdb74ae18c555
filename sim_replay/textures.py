"""Procedural surface textures with structure from a few millimetres up.

NI-SLAM correlates gray images at a few millimetres per cell and FastORB needs
corners, so every material carries contrast at every scale: multi-octave value
noise down to one texel, small blobs and spots, and man-made edges (planks,
tiles, posters, labels). A texture depends only on its material, size and
seed, so a scene looks the same on every run with the same seed.

Pure numpy/OpenCV; textures are BGR uint8 with texel centres at
((col + 0.5) * texel_m, (row + 0.5) * texel_m) on the surface.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from onboard import NislamError

# Base colours (BGR, 0..1) per material.
_BASE_BGR = {
    "plaster": (0.78, 0.80, 0.82),
    "wood": (0.30, 0.47, 0.62),
    "tiles": (0.80, 0.82, 0.80),
    "tiles_floor": (0.55, 0.58, 0.60),
    "cardboard": (0.36, 0.52, 0.66),
    "concrete": (0.58, 0.58, 0.56),
    "paint": (0.74, 0.76, 0.78),  # plain emulsion: no grain, no spots (textureless to keypoints)
}
MATERIALS = tuple(_BASE_BGR)


def value_noise(rng: np.random.Generator, shape: tuple[int, int], cell_px: tuple[float, float]
                ) -> np.ndarray:
    """Smooth random field of unit-ish std with features `cell_px` (rows, cols) apart:
    Gaussian values on a coarse grid, bicubic up-sampling."""
    h, w = shape
    cy, cx = max(cell_px[0], 1.0), max(cell_px[1], 1.0)
    gh, gw = int(math.ceil(h / cy)) + 3, int(math.ceil(w / cx)) + 3
    grid = rng.standard_normal((gh, gw), dtype=np.float32)
    if cy <= 1.0 and cx <= 1.0:
        return grid[:h, :w]
    up = cv2.resize(grid, (int(round(gw * cx)), int(round(gh * cy))), interpolation=cv2.INTER_CUBIC)
    return up[:h, :w]


def fbm(rng: np.random.Generator, shape: tuple[int, int], finest_px: float, coarsest_px: float,
        gain: float = 0.85, stretch: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """Sum of value-noise octaves from `finest_px` to `coarsest_px`, each twice
    the size of the last with amplitude x `gain` per finer octave (gain near 1
    keeps the fine octaves strong); normalised to std 1."""
    out = np.zeros(shape, np.float32)
    cell, amp = coarsest_px, 1.0
    while cell >= finest_px * 0.999:
        out += amp * value_noise(rng, shape, (cell * stretch[0], cell * stretch[1]))
        cell, amp = cell / 2.0, amp * gain
    std = float(out.std())
    return out / std if std > 0 else out


def _spots(rng: np.random.Generator, img: np.ndarray, per_m2: float, texel_m: float,
           radius_m: tuple[float, float], strength: float) -> None:
    """Random soft round spots (dirt, print dots, knots), darker or lighter, in
    place: impulses blurred per size band, vectorised (a wall holds ~10^4)."""
    h, w = img.shape[:2]
    n_total = int(per_m2 * h * w * texel_m * texel_m)
    bands = np.geomspace(radius_m[0], radius_m[1], 3)
    layer = np.zeros((h, w), np.float32)
    for r_m in bands:
        n = n_total // len(bands)
        if n == 0:
            continue
        band = np.zeros((h, w), np.float32)
        idx = rng.integers(0, h * w, n)
        band.flat[idx] = rng.uniform(-strength, strength, n).astype(np.float32)
        sigma = 0.5 * r_m / texel_m
        if sigma >= 0.5:
            # A unit impulse blurred by sigma peaks at 1 / (2 pi sigma^2).
            band = cv2.GaussianBlur(band, (0, 0), sigma) * np.float32(2.0 * math.pi * sigma**2)
        layer += band
    img += layer[..., None]


def _rectangles(rng: np.random.Generator, img: np.ndarray, count: int, texel_m: float,
                size_m: tuple[float, float]) -> None:
    """Posters / labels: rectangles of their own colour and pattern, with a frame."""
    h, w = img.shape[:2]
    for _ in range(count):
        rw = int(rng.uniform(*size_m) / texel_m)
        rh = int(rng.uniform(*size_m) / texel_m)
        if rw >= w or rh >= h or rw < 4 or rh < 4:
            continue
        x0, y0 = int(rng.integers(0, w - rw)), int(rng.integers(0, h - rh))
        colour = rng.uniform(0.1, 0.9, 3).astype(np.float32)
        cell = float(rng.uniform(1.5, 6.0))
        pattern = fbm(rng, (rh, rw), cell, max(cell * 8, 32.0), gain=0.8)
        img[y0:y0 + rh, x0:x0 + rw] = colour * (1.0 + 0.35 * pattern[..., None])
        frame = max(1, int(0.006 / texel_m))
        cv2.rectangle(img, (x0, y0), (x0 + rw - 1, y0 + rh - 1), (0.05, 0.05, 0.05), frame)


def _lines(img: np.ndarray, spacing_px: float, width_px: int, value: float, axis: int,
           jitter: np.ndarray | None = None) -> None:
    """Grout lines or plank gaps every `spacing_px` along `axis` (0 rows, 1 cols)."""
    h, w = img.shape[:2]
    n = int((h if axis == 0 else w) / spacing_px) + 1
    for k in range(1, n):
        pos = int(k * spacing_px + (0 if jitter is None else jitter[k % len(jitter)]))
        if axis == 0:
            img[max(pos - width_px // 2, 0):pos + (width_px + 1) // 2] = value
        else:
            img[:, max(pos - width_px // 2, 0):pos + (width_px + 1) // 2] = value


def make_texture(material: str, size_px: tuple[int, int], texel_m: float, seed: int,
                 shade: float = 1.0) -> np.ndarray:
    """A (rows, cols, 3) uint8 BGR texture of `material` at `texel_m` per texel.

    `shade` scales the brightness (baked Lambertian light: floors are brighter
    than ceilings); `seed` (with the material) fixes every random choice.
    """
    if material not in _BASE_BGR:
        raise NislamError(f"unknown material {material!r} (known: {', '.join(MATERIALS)})")
    rng = np.random.default_rng(seed)
    h, w = size_px
    px = 1.0 / texel_m  # texels per metre
    base = np.array(_BASE_BGR[material], np.float32)
    # Fine grain (1 texel .. ~1 cm) carries the correlation signal; the coarse
    # octaves (to ~0.5 m) add the blotchy light and dirt a real wall has.
    grain = fbm(rng, (h, w), 1.0, max(0.01 * px, 2.0), gain=0.9)
    blotch = fbm(rng, (h, w), max(0.02 * px, 2.0), max(0.5 * px, 4.0), gain=0.7)
    img = np.empty((h, w, 3), np.float32)
    img[:] = base
    if material == "wood":
        streaks = fbm(rng, (h, w), 1.0, 0.05 * px, gain=0.9, stretch=(1.0, 12.0))
        plank_px = 0.14 * px
        n_planks = int(h / plank_px) + 2
        tint = rng.uniform(0.8, 1.2, n_planks).astype(np.float32)
        rows = np.minimum((np.arange(h) / plank_px).astype(int), n_planks - 1)
        img *= tint[rows][:, None, None]
        img *= (1.0 + 0.22 * streaks + 0.12 * grain + 0.08 * blotch)[..., None]
        _lines(img, plank_px, max(1, int(0.004 * px)), 0.08, axis=0)
        _spots(rng, img, 60.0, texel_m, (0.002, 0.012), 0.25)
    elif material in ("tiles", "tiles_floor"):
        img *= (1.0 + 0.25 * grain + 0.08 * blotch)[..., None]
        _spots(rng, img, 2500.0, texel_m, (0.0015, 0.004), 0.3)
        tile_px = (0.6 if material == "tiles" else 0.4) * px
        _lines(img, tile_px, max(1, int(0.006 * px)), 0.25, axis=0)
        _lines(img, tile_px, max(1, int(0.006 * px)), 0.25, axis=1)
    elif material == "cardboard":
        img *= (1.0 + 0.2 * grain + 0.1 * blotch)[..., None]
        _spots(rng, img, 400.0, texel_m, (0.002, 0.01), 0.25)
        area_m2 = h * w * texel_m * texel_m
        _rectangles(rng, img, max(1, int(4 * area_m2)), texel_m, (0.05, 0.25))
    elif material == "concrete":
        img *= (1.0 + 0.28 * grain + 0.15 * blotch)[..., None]
        _spots(rng, img, 1500.0, texel_m, (0.001, 0.006), 0.35)
    elif material == "paint":
        # Plain emulsion: a faint mottle (2-10 cm, ~5 grey levels) and broad
        # unevenness, far below a keypoint detector's corner contrast (FAST
        # threshold 20 after CLAHE), yet a pattern for dense correlation.
        mottle = fbm(rng, (h, w), max(0.02 * px, 2.0), max(0.1 * px, 4.0), gain=0.8)
        img *= (1.0 + 0.025 * mottle + 0.06 * blotch)[..., None]
    else:  # plaster
        img *= (1.0 + 0.2 * grain + 0.1 * blotch)[..., None]
        _spots(rng, img, 600.0, texel_m, (0.002, 0.015), 0.3)
        area_m2 = h * w * texel_m * texel_m
        _rectangles(rng, img, max(1, int(0.4 * area_m2)), texel_m, (0.3, 1.0))
    img *= np.float32(shade)
    return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)


def mip_levels(texture: np.ndarray, levels: int) -> list[np.ndarray]:
    """Box-filtered halvings (INTER_AREA): level k texel j covers level-0
    texels 2^k j .. 2^k (j+1) - 1, so all levels share one texel-centre rule."""
    out = [texture]
    for _ in range(1, levels):
        prev = out[-1]
        h, w = prev.shape[:2]
        if h < 2 or w < 2:
            break
        out.append(cv2.resize(prev, (w // 2, h // 2), interpolation=cv2.INTER_AREA))
    return out
