"""FastORB key frames: landmarks from depth, descriptors, the local map of
recent key frames, and the key frames' clouds for the dense map."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from onboard.core.messages import KeyframeCloud
from onboard.core.se3 import camera_in_world
from onboard.fastorb.kernels import depth_at


def sample_depth(
    depth_m: np.ndarray,
    uv: np.ndarray,
    min_depth_m: float,
    max_depth_m: float,
    edge_rel: float,
) -> np.ndarray:
    """Depth (N,) at the sub-pixel positions `uv`, bilinear between the four
    pixel centres around each (on a slanted floor the nearest pixel's depth
    is off by up to half a pixel's worth of slope); 0 where unusable: out of
    range, or on a depth edge (the 4 x 4 pixels around it span more than
    `edge_rel` of the depth), where a corner's depth belongs to either surface."""
    if len(uv) == 0:
        return np.zeros(0)
    return depth_at(depth_m, uv, min_depth_m, max_depth_m, edge_rel)  # compiled


@dataclass
class Keyframe:
    """A key frame: pose, equalised image, keypoints with ORB descriptors and
    their landmarks. `uv` is where each landmark sits in this image (a
    tracked point's own pixel when the keypoint took over its landmark), so
    LK from here lands on the landmark. `bgr` / `depth_m` are kept only until
    its cloud has been handed over."""

    keyframe_id: int
    t_s: float
    T_cw: np.ndarray
    gray: np.ndarray  # (H, W) uint8, equalised as the tracker sees it
    uv: np.ndarray  # (N, 2) landmark pixels in this key frame
    desc: np.ndarray  # (N, 32) uint8 ORB descriptors
    xyz_W: np.ndarray  # (N, 3) landmarks in the world
    ids: np.ndarray  # (N,) landmark ids: the same physical point keeps its id and position
    bgr: np.ndarray | None
    depth_m: np.ndarray | None
    z: np.ndarray | None = None  # (N,) depth measured at uv [m], 0: none (local BA)

    def __post_init__(self) -> None:
        self.set_pose(self.T_cw)

    def set_pose(self, T_cw: np.ndarray) -> None:
        self.T_cw = T_cw
        self.centre_W = camera_in_world(T_cw)[0]
        self.axis_W = T_cw[2, :3].copy()  # optical axis in the world: row 3 of R_cw

    def drop_rows(self, rows: np.ndarray) -> None:
        """Erase these observations (rows of uv, desc, xyz_W, ids, z)."""
        keep = np.ones(len(self.ids), bool)
        keep[rows] = False
        self._keep(keep)

    def drop_ids(self, ids: np.ndarray) -> None:
        if len(ids):
            self._keep(~np.isin(self.ids, ids))

    def _keep(self, keep: np.ndarray) -> None:
        if keep.all():
            return
        self.uv, self.desc, self.xyz_W, self.ids = (
            self.uv[keep], self.desc[keep], self.xyz_W[keep], self.ids[keep])
        if self.z is not None:
            self.z = self.z[keep]

    def transform_points(self, delta_W: np.ndarray, exclude: np.ndarray) -> None:
        """Move the landmarks (but those with ids in `exclude`) by the rigid
        world motion delta_W."""
        sel = ~np.isin(self.ids, exclude)
        if sel.any():
            self.xyz_W = self.xyz_W.copy()
            self.xyz_W[sel] = self.xyz_W[sel] @ delta_W[:3, :3].T + delta_W[:3, 3]

    def move_points(self, ids: np.ndarray, xyz_W: np.ndarray) -> None:
        """New positions for those of the landmarks `ids` (sorted) this key
        frame observes."""
        if not len(ids) or not len(self.ids):
            return
        pos = np.minimum(np.searchsorted(ids, self.ids), len(ids) - 1)
        hit = ids[pos] == self.ids
        if hit.any():
            self.xyz_W = self.xyz_W.copy()
            self.xyz_W[hit] = xyz_W[pos[hit]]


@dataclass(frozen=True)
class MapPoints:
    """Landmarks of some key frames, one row per landmark id (ascending),
    each with its descriptor and pixel in the key frame `kf` (an index into
    `keyframes`)."""

    keyframes: tuple[Keyframe, ...]
    ids: np.ndarray  # (M,) int64
    xyz_W: np.ndarray  # (M, 3)
    desc: np.ndarray  # (M, 32) uint8
    uv: np.ndarray  # (M, 2)
    kf: np.ndarray  # (M,) int64

    @classmethod
    def empty(cls) -> "MapPoints":
        return cls((), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 32), np.uint8),
                   np.zeros((0, 2)), np.zeros(0, np.int64))

    def subset(self, sel: np.ndarray) -> "MapPoints":
        return MapPoints(self.keyframes, self.ids[sel], self.xyz_W[sel], self.desc[sel],
                         self.uv[sel], self.kf[sel])

    def __len__(self) -> int:
        return len(self.ids)

    def has(self, ids: np.ndarray) -> np.ndarray:
        """Which rows (bool (M,)) have one of `ids` (np.isin by binary search:
        the rows are sorted by id)."""
        hit = np.zeros(len(self.ids), bool)
        if len(self.ids) and len(ids):
            pos = np.minimum(np.searchsorted(self.ids, ids), len(self.ids) - 1)
            hit[pos[self.ids[pos] == ids]] = True
        return hit


class LocalMap:
    """The key frames kept for re-localisation (newest last). The local map
    that tracking matches against is the landmarks of the `local` key frames
    looking most like the current view (optical axes within
    `max_view_angle_deg`, nearest first), so a view seen minutes ago is found
    again as long as its key frame is kept."""

    def __init__(self, max_keyframes: int, local: int, max_view_angle_deg: float = 60.0):
        self._kfs: deque[Keyframe] = deque(maxlen=max(max_keyframes, local, 1))
        self._local = local
        self._cos_max = float(np.cos(np.radians(max_view_angle_deg)))
        self._cached: tuple[tuple[int, ...], MapPoints] = ((), MapPoints.empty())
        self._views: tuple[np.ndarray, np.ndarray] | None = None  # (axes, centres) of _kfs

    def __len__(self) -> int:
        return len(self._kfs)

    @property
    def newest(self) -> Keyframe | None:
        return self._kfs[-1] if self._kfs else None

    def add(self, kf: Keyframe) -> None:
        self._kfs.append(kf)
        self._views = None

    def clear(self) -> None:
        self._kfs.clear()
        self._cached = ((), MapPoints.empty())
        self._views = None

    def keyframes(self) -> list[Keyframe]:
        """All kept key frames, oldest first."""
        return list(self._kfs)

    def remove(self, keyframe_id: int) -> None:
        for kf in self._kfs:
            if kf.keyframe_id == keyframe_id:
                self._kfs.remove(kf)
                break
        self.changed()

    def changed(self) -> None:
        """Key frames moved, removed or their landmarks changed: rebuild the
        cached views and local-map points."""
        self._cached = ((), MapPoints.empty())
        self._views = None

    def newest_first(self, n: int) -> list[Keyframe]:
        return list(self._kfs)[::-1][:n]

    def reloc_candidates(self, cursor: int, n: int) -> tuple[list[Keyframe], int]:
        """Key frames to try for one lost frame, and the next cursor: the two
        newest, then the next `n` of all kept ones in turn (newest to oldest,
        wrapping), so a long loss works through the whole map a few at a
        time. Key frames made just before a loss are often blurred and useless."""
        kfs = self.newest_first(len(self._kfs))
        rest = kfs[2:]
        if not rest:
            return kfs, cursor
        n = min(n, len(rest))
        start = cursor % len(rest)
        return kfs[:2] + [rest[(start + i) % len(rest)] for i in range(n)], start + n

    def nearest(self, T_cw: np.ndarray, n: int) -> list[Keyframe]:
        """Up to `n` key frames by view similarity to the pose T_cw: optical
        axes within the angle limit, ranked by angle plus 1 rad per metre of
        camera distance."""
        if not self._kfs:
            return []
        axis = T_cw[2, :3]  # optical axis in the world: row 3 of R_cw
        centre = camera_in_world(T_cw)[0]
        if self._views is None:  # rebuilt only when the key frames change
            self._views = (np.array([k.axis_W for k in self._kfs]),
                           np.array([k.centre_W for k in self._kfs]))
        axes, centres = self._views
        cosines = axes @ axis
        dists = np.linalg.norm(centres - centre, axis=1)
        score = np.arccos(np.clip(cosines, -1.0, 1.0)) + dists
        order = [i for i in np.argsort(score) if cosines[i] >= self._cos_max][:n]
        kfs = list(self._kfs)
        return [kfs[i] for i in order]

    def points_near(self, T_cw: np.ndarray) -> MapPoints:
        """The landmarks of the key frames nearest to T_cw, each id once, seen
        from the nearest key frame that has it."""
        kfs = tuple(self.nearest(T_cw, self._local))
        key = tuple(k.keyframe_id for k in kfs)
        if key != self._cached[0]:  # the same key frames frame after frame, mostly
            self._cached = (key, _gather(kfs))
        return self._cached[1]


def _gather(kfs: tuple[Keyframe, ...]) -> MapPoints:
    """The landmarks of `kfs`, each id once, from the first key frame that has it."""
    if not kfs:
        return MapPoints.empty()
    ids = np.concatenate([k.ids for k in kfs])
    _, first = np.unique(ids, return_index=True)
    return MapPoints(
        kfs,
        ids[first],
        np.concatenate([k.xyz_W for k in kfs])[first],
        np.concatenate([k.desc for k in kfs])[first],
        np.concatenate([k.uv for k in kfs])[first],
        np.concatenate([np.full(len(k.ids), i) for i, k in enumerate(kfs)])[first],
    )


def _quantile(a: np.ndarray, q: float) -> float:
    """np.quantile(a, q) (linear interpolation) by one partition, without
    its generic overhead."""
    pos = q * (len(a) - 1)
    lo = int(np.floor(pos))
    hi = min(lo + 1, len(a) - 1)
    part = np.partition(a, [lo, hi])
    return float(np.quantile(part[[lo, hi]], pos - lo))


def keyframe_cloud(
    kf: Keyframe, K: np.ndarray, stride: int, min_depth_m: float, max_depth_m: float
) -> KeyframeCloud | None:
    """The key frame's depth as a `KeyframeCloud` (the NI-SLAM key-image form:
    an axonometric grid in key axes, nearest point per cell), so the replay's
    map writer takes FastORB keys unchanged. Every `stride`-th pixel; the grid
    has the sampled image's size and a resolution that holds 95 % of the
    points. Drops the key frame's images afterwards."""
    grid = cloud_grid(kf, K, stride, min_depth_m, max_depth_m)
    return None if grid is None else grid_cloud(kf, grid)


CloudGrid = tuple[float, np.ndarray, np.ndarray, np.ndarray]  # (res, depth, gray, bgr)


def grid_cloud(kf: Keyframe, grid: CloudGrid) -> KeyframeCloud:
    """The cloud of `cloud_grid` at the key frame's pose now."""
    p_W, R_W_C = camera_in_world(kf.T_cw)
    return KeyframeCloud(kf.keyframe_id, kf.t_s, p_W, R_W_C, *grid)


def cloud_grid(
    kf: Keyframe, K: np.ndarray, stride: int, min_depth_m: float, max_depth_m: float
) -> CloudGrid | None:
    """keyframe_cloud's grid (resolution, depth, gray, colour), which the
    pose does not enter; None without images or with under 10 points.
    Drops the key frame's images."""
    bgr, depth = kf.bgr, kf.depth_m
    kf.bgr = kf.depth_m = None
    if bgr is None or depth is None:
        return None
    z = depth[::stride, ::stride].astype(np.float64)
    h, w = z.shape
    vv, uu = np.nonzero((z > min_depth_m) & (z < max_depth_m))
    if len(vv) < 10:
        return None
    zz = z[vv, uu]
    x = (uu * stride - K[0, 2]) / K[0, 0] * zz
    y = (vv * stride - K[1, 2]) / K[1, 1] * zz
    res = max(_quantile(np.abs(x), 0.95) / (w // 2), _quantile(np.abs(y), 0.95) / (h // 2), 1e-3)
    cu = np.floor(x / res + w // 2).astype(np.int64)
    cv = np.floor(y / res + h // 2).astype(np.int64)
    ok = np.flatnonzero((cu >= 0) & (cu < w) & (cv >= 0) & (cv < h))
    cell = (cv * w + cu)[ok]
    # By cell, nearest first, in one stable sort: depths are below 1e3 m, so
    # cell * 1e3 + z orders as (cell, z) does.
    order = np.argsort(cell * 1e3 + zz[ok], kind="stable")
    cell = cell[order]
    first = np.flatnonzero(np.r_[True, cell[1:] != cell[:-1]])
    pick = ok[order[first]]
    grid_depth = np.zeros((h, w), np.float32)
    grid_bgr = np.zeros((h, w, 3), np.uint8)
    grid_depth.flat[cell[first]] = zz[pick]
    grid_bgr.reshape(-1, 3)[cell[first]] = bgr[vv[pick] * stride, uu[pick] * stride]
    wide = grid_bgr.astype(np.float32)
    gray = (wide[..., 0] + wide[..., 1] + wide[..., 2]) / np.float32(3.0) / np.float32(255.0)
    return float(res), grid_depth, gray, grid_bgr
