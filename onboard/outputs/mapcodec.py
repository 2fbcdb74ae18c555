"""The compact binary encoding of one map key frame (zenoh `map/keyframe/<id>`).

A refined key frame is a grid: each filled cell (u, v) of the key's
axonometric depth image is one point. Instead of 15 bytes of float32 xyz +
colour per point, the message carries the grid's occupancy as a bit mask, one
depth value and one colour per filled cell, and the key's pose; the receiver
places the points exactly as `KeyframeCloud.points()` does. That halves the
size (about 7 bytes per point plus H*W/8 bytes of mask) without compression,
so encoding costs a few milliseconds on the publisher's thread.

Layout, version 1, all little-endian, 136-byte header then three blocks:

    offset size  field
       0    4    magic b"NSKF"
       4    1    version = 1
       5    1    depth sample size in bytes: 4 (float32) or 8 (float64)
       6    2    reserved, 0
       8    4    keyframe_id, int32
      12    2    grid height H, uint16
      14    2    grid width W, uint16
      16    4    N = number of filled cells (points), uint32
      20    4    reserved, 0
      24    8    t_s, float64: the key's capture time
      32   24    p_W_m, 3 x float64: key camera position in the world W [m]
      56   72    R_W_C, 9 x float64, row-major: key camera orientation
     128    8    res_m, float64: grid cell size [m]
     136    ceil(H*W/8)  occupancy mask, row-major, bit k of byte j = cell 8j+k
                         (numpy.packbits(..., bitorder="little"))
       .    N x 4|8      depth of each filled cell, row-major cell order [m]
       .    N x 3        colour of each filled cell, uint8 r, g, b

A point of filled cell (u, v) (column u, row v) in key camera axes is
((u - W//2 + 0.5) * res_m, (v - H//2 + 0.5) * res_m, depth), in the world
R_W_C @ that + p_W_m, computed in float64 and stored as float32: exactly
`KeyframeCloud.points()`. The colour is the key's own colour, or its refined
gray where the key saw nothing (as `points()` picks it). Decoding gives the
same arrays bit for bit.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, replace

import numpy as np

from onboard import NislamError
from onboard.core.messages import KeyframeCloud

MAGIC = b"NSKF"
VERSION = 1
ENCODING = "application/octet-stream;nislam-keyframe/1"  # zenoh encoding string
_HEADER = struct.Struct("<4sBBHiHHII4d9dd")
assert _HEADER.size == 136
_DEPTH_DTYPES = {4: np.dtype("<f4"), 8: np.dtype("<f8")}


class MapCodecError(NislamError):
    """A key-frame message that cannot be decoded."""


@dataclass(frozen=True)
class MapKeyframe:
    """A key frame as carried on the wire: pose, grid occupancy and one depth
    and colour per filled cell (row-major cell order)."""

    keyframe_id: int
    t_s: float
    p_W_m: np.ndarray  # (3,) float64
    R_W_C: np.ndarray  # (3, 3) float64
    res_m: float
    mask: np.ndarray  # (H, W) bool, True = filled cell
    depth_m: np.ndarray  # (N,) float32 or float64
    rgb: np.ndarray  # (N, 3) uint8

    @classmethod
    def from_cloud(cls, kf: KeyframeCloud) -> MapKeyframe:
        """The wire form of a tracker's key frame; `points()` of the result
        equals `kf.points()` bit for bit."""
        mask = kf.depth_m > 0
        vv, uu = np.nonzero(mask)
        depth = kf.depth_m[vv, uu]
        if depth.dtype not in (np.float32, np.float64):
            depth = depth.astype(np.float64)
        rgb = kf.bgr[vv, uu, ::-1].copy()
        no_colour = ~rgb.any(axis=1)
        rgb[no_colour] = np.clip(kf.gray[vv, uu][no_colour] * 255.0 + 0.5, 0, 255)[:, None]
        return cls(
            int(kf.keyframe_id), float(kf.t_s),
            np.asarray(kf.p_W_m, dtype=np.float64).reshape(3),
            np.asarray(kf.R_W_C, dtype=np.float64).reshape(3, 3),
            float(kf.res_m), mask, depth, rgb.astype(np.uint8),
        )

    @property
    def num_points(self) -> int:
        return len(self.depth_m)

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """(xyz_W_m (N,3) float32, rgb (N,3) uint8), the formula of
        `KeyframeCloud.points()` step by step."""
        h, w = self.mask.shape
        vv, uu = np.nonzero(self.mask)
        s = self.res_m
        pts = np.stack([(uu - w // 2 + 0.5) * s, (vv - h // 2 + 0.5) * s, self.depth_m], axis=1)
        xyz = (pts @ self.R_W_C.T + self.p_W_m).astype(np.float32)
        return xyz, self.rgb


@dataclass(frozen=True)
class KeyframeMove:
    """A key frame the tracker moved (a loop closure): the same cells (they
    are in key axes) at a new pose."""

    keyframe_id: int
    p_W_m: np.ndarray
    R_W_C: np.ndarray

    def applied(self, data: bytes) -> MapKeyframe:
        """The encoded key frame `data` at this pose."""
        return replace(decode_keyframe(data), p_W_m=np.asarray(self.p_W_m, np.float64),
                       R_W_C=np.asarray(self.R_W_C, np.float64))


def encode_keyframe(kf: KeyframeCloud | MapKeyframe) -> bytes:
    """One key frame in the layout of the module docstring."""
    m = kf if isinstance(kf, MapKeyframe) else MapKeyframe.from_cloud(kf)
    h, w = m.mask.shape
    if h > 0xFFFF or w > 0xFFFF:
        raise ValueError(f"grid {h}x{w} is too large for the key-frame encoding")
    depth = m.depth_m.astype(m.depth_m.dtype.newbyteorder("<"), copy=False)
    header = _HEADER.pack(
        MAGIC, VERSION, depth.dtype.itemsize, 0, m.keyframe_id, h, w, m.num_points, 0,
        m.t_s, *m.p_W_m.tolist(), *m.R_W_C.reshape(9).tolist(), m.res_m,
    )
    bits = np.packbits(m.mask.reshape(-1), bitorder="little")
    rgb = np.ascontiguousarray(m.rgb, dtype=np.uint8)
    return b"".join((header, bits.tobytes(), depth.tobytes(), rgb.tobytes()))


def decode_keyframe(data: bytes | bytearray | memoryview) -> MapKeyframe:
    """The key frame in `data`; MapCodecError when it is not one."""
    buf = memoryview(data).cast("B")
    if len(buf) < _HEADER.size:
        raise MapCodecError(f"key-frame message too short ({len(buf)} bytes)")
    (magic, version, dsize, _r0, kid, h, w, n, _r1, t_s, *rest) = _HEADER.unpack_from(buf)
    if magic != MAGIC:
        raise MapCodecError(f"not a key-frame message (magic {magic!r})")
    if version != VERSION:
        raise MapCodecError(f"key-frame encoding version {version} (this build reads {VERSION})")
    if dsize not in _DEPTH_DTYPES:
        raise MapCodecError(f"key-frame depth sample size {dsize} (4 or 8 expected)")
    p_W = np.array(rest[0:3], dtype=np.float64)
    R_W_C = np.array(rest[3:12], dtype=np.float64).reshape(3, 3)
    res_m = float(rest[12])
    mask_len = (h * w + 7) // 8
    expected = _HEADER.size + mask_len + n * dsize + n * 3
    if len(buf) != expected:
        raise MapCodecError(f"key-frame message is {len(buf)} bytes, its header says {expected}")
    off = _HEADER.size
    mask = np.unpackbits(
        np.frombuffer(buf, np.uint8, mask_len, off), count=h * w, bitorder="little"
    ).astype(bool).reshape(h, w)
    if int(mask.sum()) != n:
        raise MapCodecError(f"key-frame mask holds {int(mask.sum())} cells, header says {n}")
    off += mask_len
    depth = np.frombuffer(buf, _DEPTH_DTYPES[dsize], n, off).copy()
    off += n * dsize
    rgb = np.frombuffer(buf, np.uint8, n * 3, off).reshape(n, 3).copy()
    return MapKeyframe(int(kid), float(t_s), p_W, R_W_C, res_m, mask, depth, rgb)


def map_digest(crc_by_id: dict[int, int]) -> str:
    """One 8-hex-digit digest of a set of key frames (each id with the CRC-32
    of its message): the vehicle's status carries it, and a ground station
    whose own digest differs fetches the map again (a key frame missed, or
    one re-published after a refinement)."""
    body = b"".join(struct.pack("<iI", k, crc_by_id[k]) for k in sorted(crc_by_id))
    return f"{zlib.crc32(body):08x}"
