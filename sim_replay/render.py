"""Exact analytic rendering of a `Scene` to colour and depth.

Every surface is a plane, so for a pinhole camera its inverse depth is affine
in the pixel coordinates, 1/z = a u + b v + c, and its texture coordinates
are a homography of them. Per visible tile of a surface the renderer

  1. clips the tile against the near plane and rasterises its outline (mask),
  2. evaluates 1/z exactly at every pixel centre of the tile's bounding box
     (float64) and keeps the pixels nearer than the z-buffer,
  3. warps the texture through the homography (cv2.warpPerspective) at the
     mip level matching the pixel footprint, and copies the kept pixels.

Depth is therefore exact at pixel centres (to float rounding); colour is the
texture as a pinhole camera with a box-filtering pixel would see it, to a mip
level. Back-facing and out-of-frustum tiles are culled before any per-pixel
work. Pixel (u, v) has its centre at integer coordinates, as in OpenCV and in
`onboard.nislam.projection` (ray ((u - cx) / fx, (v - cy) / fy, 1)).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import cv2
import numpy as np

from onboard.core.camera import CameraIntrinsics
from sim_replay.scene import Scene
from sim_replay.textures import make_texture, mip_levels

log = logging.getLogger(__name__)

NEAR_M = 0.05  # near clipping plane: nothing is rendered closer (sensors see nothing there)
TILE_M = 2.0  # surfaces are cut into tiles of at most this size: mip level and culling per tile
MIP_LEVELS = 6  # texel to 32 texels (10 cm at 3 mm): a pixel's footprint beyond any wall here
_FIX_SHIFT = 4  # sub-pixel bits of the polygon rasteriser
# Light from above (z down): floors are lit, ceilings only by the bounce.
_LIGHT_W = np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0])


@dataclass(frozen=True)
class RenderOutput:
    """One rendered view. `bgr` (H, W, 3) uint8; `depth_m` (H, W) float32 along
    the optical axis (0 where nothing was hit); `surface_id` (H, W) int16 index
    into scene.surfaces (-1 = none), only when asked for."""

    bgr: np.ndarray
    depth_m: np.ndarray
    surface_id: np.ndarray | None = None


@dataclass
class _SurfaceTexture:
    levels: list[np.ndarray]
    texel_m: float


class Renderer:
    """Renders one scene for one pinhole camera; textures are built lazily the
    first time a surface is seen (a short flight never pays for the rest).

    `seed` fixes the textures. Not thread-safe (texture cache).
    """

    def __init__(self, scene: Scene, intrinsics: CameraIntrinsics, seed: int = 0,
                 texel_m: float = 0.003) -> None:
        if texel_m <= 0:
            raise ValueError("texel_m must be > 0")
        self.scene = scene
        self.intr = intrinsics
        self.seed = seed
        self.texel_m = texel_m
        self._k = np.array([[intrinsics.fx, 0.0, intrinsics.cx],
                            [0.0, intrinsics.fy, intrinsics.cy], [0.0, 0.0, 1.0]])
        self._k_inv = np.linalg.inv(self._k)
        self._u = np.arange(intrinsics.width, dtype=np.float64)
        self._v = np.arange(intrinsics.height, dtype=np.float64)
        self._textures: dict[int, _SurfaceTexture] = {}
        self.texture_build_s = 0.0  # CPU time spent building textures (first sight of a surface)
        self._build_tiles()

    # ------------------------------------------------------------------ setup

    def _build_tiles(self) -> None:
        """Cut every surface into tiles of at most TILE_M; arrays for culling."""
        corners, owner = [], []
        for i, s in enumerate(self.scene.surfaces):
            nu = max(1, math.ceil(s.size_m[0] / TILE_M - 1e-9))
            nv = max(1, math.ceil(s.size_m[1] / TILE_M - 1e-9))
            au = np.linspace(0.0, s.size_m[0], nu + 1)
            av = np.linspace(0.0, s.size_m[1], nv + 1)
            for j in range(nu):
                for k in range(nv):
                    c = np.stack([
                        s.origin_W_m + au[a] * s.axis_u + av[b] * s.axis_v
                        for a, b in ((j, k), (j + 1, k), (j + 1, k + 1), (j, k + 1))
                    ])
                    corners.append(c)
                    owner.append(i)
        self._tile_corners_W = np.asarray(corners)  # (T, 4, 3)
        self._tile_surface = np.asarray(owner)
        self._normals_W = np.stack([s.normal for s in self.scene.surfaces])  # (S, 3)
        self._origins_W = np.stack([s.origin_W_m for s in self.scene.surfaces])
        self._axes_u_W = np.stack([s.axis_u for s in self.scene.surfaces])
        self._axes_v_W = np.stack([s.axis_v for s in self.scene.surfaces])
        log.debug("%s: %d surfaces in %d tiles", self.scene.name, len(self.scene.surfaces),
                  len(corners))

    def texture(self, index: int) -> _SurfaceTexture:
        """The mip chain of surface `index`, built on first use."""
        tex = self._textures.get(index)
        if tex is None:
            t0 = time.thread_time()
            s = self.scene.surfaces[index]
            # Sizes rounded up to a multiple of 2^(levels-1): every halving is exact,
            # so all levels agree on where a surface point is.
            m = 2 ** (MIP_LEVELS - 1)
            cols = m * math.ceil(s.size_m[0] / self.texel_m / m)
            rows = m * math.ceil(s.size_m[1] / self.texel_m / m)
            shade = 0.55 + 0.45 * max(0.0, float(-s.normal @ _LIGHT_W))
            seed = [self.seed, index, sum(map(ord, s.name))]
            base = make_texture(s.material, (rows, cols), self.texel_m,
                                int(np.random.SeedSequence(seed).generate_state(1)[0]), shade)
            tex = _SurfaceTexture(mip_levels(base, MIP_LEVELS), self.texel_m)
            self._textures[index] = tex
            self.texture_build_s += time.thread_time() - t0
        return tex

    def built_textures(self) -> dict[int, list[np.ndarray]]:
        """The mip chains built so far, by surface index (to keep on disk)."""
        return {i: t.levels for i, t in self._textures.items()}

    def adopt_textures(self, levels_by_surface: dict[int, list[np.ndarray]]) -> None:
        """Use mip chains built earlier for this scene, seed and texel size
        (sim_replay.follow keeps them on disk: building the room's takes seconds)."""
        for i, levels in levels_by_surface.items():
            self._textures[int(i)] = _SurfaceTexture(list(levels), self.texel_m)

    # ---------------------------------------------------------------- render

    def render(self, R_W_C: np.ndarray, p_W_m: np.ndarray, with_ids: bool = False
               ) -> RenderOutput:
        """Colour and exact depth seen by a camera at pose (R_W_C, p_W_m)."""
        h, w = self.intr.height, self.intr.width
        R_C_W = np.asarray(R_W_C, dtype=np.float64).T
        p = np.asarray(p_W_m, dtype=np.float64)
        inv_z = np.zeros((h, w), np.float64)  # 0 = nothing hit yet (infinitely far)
        bgr = np.zeros((h, w, 3), np.uint8)
        ids = np.full((h, w), -1, np.int16) if with_ids else None

        # Back-face culling per surface: the camera must be on the normal's side.
        facing = np.einsum("ij,ij->i", self._normals_W, p - self._origins_W) > 1e-9
        tiles = np.flatnonzero(facing[self._tile_surface])
        corners_C = (self._tile_corners_W[tiles] - p) @ R_C_W.T  # (T, 4, 3)
        keep = self._in_frustum(corners_C)
        tiles, corners_C = tiles[keep], corners_C[keep]
        if len(tiles) == 0:
            return RenderOutput(bgr, np.zeros((h, w), np.float32), ids)
        surf = self._tile_surface[tiles]
        planes = self._planes_in_camera(R_C_W, p)
        levels = self._mip_levels(corners_C, planes["n_c"][surf])
        # Front to back: nearer tiles fill the z-buffer first, so farther ones
        # copy fewer pixels.
        order = np.argsort(np.maximum(corners_C[..., 2].min(axis=1), 0.0))
        for t in order.tolist():
            self._draw_tile(int(surf[t]), corners_C[t], int(levels[t]), planes, inv_z, bgr, ids)

        depth = np.zeros((h, w), np.float32)
        hit = inv_z > 0
        depth[hit] = 1.0 / inv_z[hit]
        return RenderOutput(bgr, depth, ids)

    def _in_frustum(self, corners_C: np.ndarray) -> np.ndarray:
        """Tiles not entirely outside one of the frustum's five half-spaces.

        The side planes pass through the camera centre and the image border
        (half a pixel out); being planes, they sort corners behind the camera
        correctly too, and a convex tile with every corner outside one of
        them cannot reach the image.
        """
        x, y, z = corners_C[..., 0], corners_C[..., 1], corners_C[..., 2]
        i = self.intr
        outside = (
            z < NEAR_M,
            x * i.fx + (i.cx + 0.5) * z < 0,  # u < -0.5
            x * i.fx + (i.cx - i.width + 0.5) * z > 0,  # u > w - 0.5
            y * i.fy + (i.cy + 0.5) * z < 0,
            y * i.fy + (i.cy - i.height + 0.5) * z > 0,
        )
        culled = np.zeros(len(corners_C), dtype=bool)
        for side in outside:
            culled |= side.all(axis=1)
        return ~culled

    def _planes_in_camera(self, R_C_W: np.ndarray, p: np.ndarray) -> dict[str, np.ndarray]:
        """Per surface, in camera coordinates: inverse-depth coefficients and
        the rows of the image-to-texel homography (all surfaces at once)."""
        n_c = self._normals_W @ R_C_W.T  # (S, 3)
        o_c = (self._origins_W - p) @ R_C_W.T
        eu_c = self._axes_u_W @ R_C_W.T
        ev_c = self._axes_v_W @ R_C_W.T
        d_c = np.einsum("ij,ij->i", n_c, o_c)  # plane n_c . X = d_c (< 0 when facing us)
        with np.errstate(divide="ignore", invalid="ignore"):
            abc = (n_c @ self._k_inv) / d_c[:, None]  # 1/z = n_c . (K^-1 [u v 1]) / d_c
        # texel (col, row) = e . (z r - o) / texel - 0.5 with z = d_c / (n_c . r):
        # homogeneously (d_c e - (e . o) n) / texel - 0.5 n over n, all times K^-1.
        hu = d_c[:, None] * eu_c - np.einsum("ij,ij->i", eu_c, o_c)[:, None] * n_c
        hv = d_c[:, None] * ev_c - np.einsum("ij,ij->i", ev_c, o_c)[:, None] * n_c
        return {"n_c": n_c, "abc": abc, "hu": hu, "hv": hv}

    def _mip_levels(self, corners_C: np.ndarray, n_c: np.ndarray) -> np.ndarray:
        """Per tile, the level whose texel matches the smallest pixel footprint
        at its corners: distance / f, stretched by 1/sqrt(cos) when oblique."""
        dist = np.linalg.norm(corners_C, axis=2)  # (T, 4)
        cos = np.abs(np.einsum("tkj,tj->tk", corners_C, n_c)) / np.maximum(dist, 1e-9)
        footprint = (dist / self.intr.fx / np.sqrt(np.maximum(cos, 0.05))).min(axis=1)
        ratio = np.maximum(footprint / self.texel_m, 1.0)
        return np.clip(np.floor(np.log2(ratio)), 0, MIP_LEVELS - 1).astype(int)

    def _draw_tile(self, si: int, corners_C: np.ndarray, level: int, planes: dict,
                   inv_z: np.ndarray, bgr: np.ndarray, ids: np.ndarray | None) -> None:
        poly = _clip_near(corners_C, NEAR_M)
        if len(poly) < 3:
            return
        i = self.intr
        u = poly[:, 0] / poly[:, 2] * i.fx + i.cx
        v = poly[:, 1] / poly[:, 2] * i.fy + i.cy
        u0, u1 = max(int(math.floor(u.min())), 0), min(int(math.ceil(u.max())), i.width - 1)
        v0, v1 = max(int(math.floor(v.min())), 0), min(int(math.ceil(v.max())), i.height - 1)
        if u0 > u1 or v0 > v1:
            return
        bw, bh = u1 - u0 + 1, v1 - v0 + 1
        mask = np.zeros((bh, bw), np.uint8)
        pts = np.round(np.stack([u - u0, v - v0], axis=1) * (1 << _FIX_SHIFT)).astype(np.int32)
        cv2.fillConvexPoly(mask, pts, 255, cv2.LINE_8, _FIX_SHIFT)
        a, b, c = planes["abc"][si]
        tile_inv_z = np.add.outer(b * self._v[v0:v1 + 1] + c, a * self._u[u0:u1 + 1])
        zbuf = inv_z[v0:v1 + 1, u0:u1 + 1]
        # OpenCV's masked compare and copy run about six times faster than
        # numpy's boolean indexing here; they write into the views in place.
        upd = cv2.compare(tile_inv_z, zbuf, cv2.CMP_GT)
        cv2.bitwise_and(upd, mask, dst=upd)
        if not cv2.countNonZero(upd):
            return
        cv2.copyTo(tile_inv_z, upd, zbuf)
        # Texture only where the tile won: the box of its visible pixels (a
        # tile half hidden behind a nearer one costs half the warp).
        x, y, ww, hh = cv2.boundingRect(upd)
        u0, v0 = u0 + x, v0 + y
        upd = upd[y:y + hh, x:x + ww]
        tex = self.texture(si)
        level = min(level, len(tex.levels) - 1)
        texel = tex.texel_m * (1 << level)
        n = planes["n_c"][si]
        rows = np.stack([planes["hu"][si] / texel - 0.5 * n, planes["hv"][si] / texel - 0.5 * n, n])
        m = rows @ self._k_inv
        m[:, 2] += m[:, 0] * u0 + m[:, 1] * v0  # box pixel -> image pixel
        warped = cv2.warpPerspective(tex.levels[level], m, (ww, hh),
                                     flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                     borderMode=cv2.BORDER_REPLICATE)
        cv2.copyTo(warped, upd, bgr[v0:v0 + hh, u0:u0 + ww])
        if ids is not None:
            ids[v0:v0 + hh, u0:u0 + ww][upd > 0] = si


def _clip_near(poly: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a convex polygon (N, 3) to z >= near."""
    z = poly[:, 2]
    if (z >= near).all():
        return poly
    out = []
    n = len(poly)
    for k in range(n):
        a, b = poly[k], poly[(k + 1) % n]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            out.append(a)
        if ina != inb:
            w = (near - a[2]) / (b[2] - a[2])
            out.append(a + w * (b - a))
    return np.asarray(out).reshape(-1, 3)
