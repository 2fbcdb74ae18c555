"""Reader for RGB-D sequences in the TUM layout.

A sequence folder holds `rgb.txt` and `depth.txt` (timestamp + relative file
name per line), optionally `groundtruth.txt`, `attitude.txt` and `camera.toml`
(see docs/design.md). The reader survives damaged recordings: malformed list
lines, repeated or out-of-order stamps, missing files, undecodable or truncated
images, all-zero depth frames, NaN and spike attitude samples are skipped;
dropped frames, clock jumps and attitude gaps are noticed. Everything is
counted in `Sequence.skipped` and reported in one summary warning instead of
one line each.
"""

from __future__ import annotations

import logging
import math
import os
import re
import struct
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field, fields
from pathlib import Path

import cv2
import numpy as np

from onboard import NislamError
from onboard.frames import CameraIntrinsics, RgbdFrame
from onboard.trajectory import Trajectory, parse_tum_lines

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - pyproject pulls tomli in for 3.10
    import tomli as tomllib

log = logging.getLogger(__name__)

DEFAULT_MAX_ASSOC_DT_S = 0.02  # TUM associate.py default: 20 ms
DEFAULT_GT_MAX_GAP_S = 0.2  # lead's decision: bridge GT gaps up to 200 ms (fr1/rpy has 130 ms)
# A forward step this long in the colour stamps is a clock jump (or an outage
# the reader cannot tell from one), not a run of dropped frames.
CLOCK_JUMP_MIN_S = 1.0
# A frame interval over 1.5 median intervals has lost round(dt / median) - 1 frames.
_DROP_GAP_FACTOR = 1.5
# An attitude sample this far from both neighbours, which agree with each other,
# is a spike: 10 deg in one 10 ms sample is 1000 deg/s, beyond what a drone that
# NI-SLAM can track turns, and far above AHRS noise (~0.1 deg).
ATTITUDE_SPIKE_DEG = 10.0

_IDENTITY_Q_XYZW = (0.0, 0.0, 0.0, 1.0)
_DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)  # what OpenCV accepts


@dataclass(frozen=True)
class CameraModel:
    """The camera as recorded: pinhole + OpenCV distortion, depth scale and mount.

    `depth_scale`: depth PNG units per metre (TUM 5000, millimetre sensors 1000,
    0 = no depth). `distortion`: OpenCV k1 k2 p1 p2 k3 (empty = none).
    `q_B_C_xyzw`: camera-optical-to-body rotation.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    depth_scale: float = 5000.0
    distortion: tuple[float, ...] = ()
    q_B_C_xyzw: tuple[float, float, float, float] = _IDENTITY_Q_XYZW

    def intrinsics(self) -> CameraIntrinsics:
        return CameraIntrinsics(self.fx, self.fy, self.cx, self.cy, self.width, self.height)

    def k_matrix(self) -> np.ndarray:
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    @property
    def is_distorted(self) -> bool:
        return any(c != 0.0 for c in self.distortion)


# Published TUM RGB-D colour intrinsics (vision.in.tum.de, "Intrinsic Camera Calibration").
_TUM_CAMERAS: dict[int, CameraModel] = {
    1: CameraModel(517.3, 516.5, 318.6, 255.3, 640, 480, 5000.0,
                   (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    2: CameraModel(520.9, 521.0, 325.1, 249.7, 640, 480, 5000.0,
                   (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    3: CameraModel(535.4, 539.2, 320.1, 247.6, 640, 480, 5000.0, ()),
}
# "fr1", "fr_1", "freiburg1" ... but not "fr12" or "frame1".
_TUM_NAME_RE = re.compile(r"(?:freiburg|fr)_?([123])(?!\d)")


@dataclass
class SkipCounts:
    """What the reader dropped or noticed, and why.

    Skipped (left out of the replay):
      malformed_lines: unparsable lines in any list, ground-truth or attitude file.
      missing_files: listed image files that do not exist.
      unreadable_files: image files that do not decode (of which
        `truncated_files` were cut short).
      unassociated: list entries (colour or depth) with no partner within the
        association window.
      duplicate_stamps / out_of_order_stamps: list entries whose stamp repeats
        or precedes one listed before them in the same list; stale entries are
        dropped as the onboard loop drops a stale frame.
      empty_depth_frames: frames whose depth image decodes but holds no
        measurement at all.
      attitude_nan_samples / attitude_spikes: attitude.txt samples with a
        non-finite value, or an isolated jump of more than ATTITUDE_SPIKE_DEG.
    Noticed (nothing to skip; the recording lacks them):
      dropped_frames: frames missing from the colour stream, from its gaps.
      clock_jumps: forward steps of at least CLOCK_JUMP_MIN_S in the colour stamps.
      attitude_gaps: gaps in attitude.txt longer than DEFAULT_GT_MAX_GAP_S (the
        replay does not bridge them), a clock jump's own gap not included.
    List-entry counts count each list: a frame repeated in both lists counts 2.
    """

    malformed_lines: int = 0
    missing_files: int = 0
    unreadable_files: int = 0
    unassociated: int = 0
    duplicate_stamps: int = 0
    out_of_order_stamps: int = 0
    truncated_files: int = 0
    empty_depth_frames: int = 0
    attitude_nan_samples: int = 0
    attitude_spikes: int = 0
    dropped_frames: int = 0
    clock_jumps: int = 0
    attitude_gaps: int = 0

    @property
    def total(self) -> int:
        """Everything skipped (`truncated_files` is part of `unreadable_files`;
        the noticed counts are not skips)."""
        return (self.malformed_lines + self.missing_files + self.unreadable_files
                + self.unassociated + self.duplicate_stamps + self.out_of_order_stamps
                + self.empty_depth_frames + self.attitude_nan_samples + self.attitude_spikes)

    @property
    def noticed(self) -> int:
        return self.dropped_frames + self.clock_jumps + self.attitude_gaps

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def summary(self) -> str:
        base = (
            f"malformed_lines={self.malformed_lines} missing_files={self.missing_files} "
            f"unreadable_files={self.unreadable_files} unassociated={self.unassociated}"
        )
        # The four historical counts always; the fault kinds only when present.
        extra = [f"{k}={v}" for k, v in self.as_dict().items()
                 if v and k not in ("malformed_lines", "missing_files", "unreadable_files",
                                    "unassociated")]
        return " ".join([base, *extra])


# --------------------------------------------------------------------------- camera


def load_camera(seq_dir: Path) -> CameraModel:
    """The sequence's camera: `camera.toml` if present, else TUM intrinsics
    chosen by the folder name (freiburg1|fr1, freiburg2|fr2, freiburg3|fr3)."""
    seq_dir = Path(seq_dir)
    toml_path = seq_dir / "camera.toml"
    if toml_path.is_file():
        return _camera_from_toml(toml_path)
    name = seq_dir.resolve().name.lower()
    found = {int(m) for m in _TUM_NAME_RE.findall(name)}
    if len(found) == 1:
        cam = _TUM_CAMERAS[found.pop()]
        log.debug("%s: no camera.toml, using TUM intrinsics from the folder name", seq_dir)
        return cam
    if len(found) > 1:
        raise NislamError(
            f"{seq_dir} has no camera.toml and its name names several TUM cameras {sorted(found)}"
        )
    raise NislamError(
        f"{seq_dir} has no camera.toml and its name names no TUM freiburg 1/2/3 camera"
    )


def _camera_from_toml(path: Path) -> CameraModel:
    try:
        raw = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as e:
        raise NislamError(f"{path}: cannot read: {e}") from None
    except tomllib.TOMLDecodeError as e:
        raise NislamError(f"{path}: not valid TOML: {e}") from None

    known = {"fx", "fy", "cx", "cy", "width", "height", "depth_scale", "distortion", "q_B_C_xyzw"}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise NislamError(f"{path}: unknown key '{unknown[0]}' (known: {', '.join(sorted(known))})")
    for key in ("fx", "fy", "cx", "cy", "width", "height", "depth_scale"):
        if key not in raw:
            raise NislamError(f"{path}: missing key '{key}'")

    def number(key: str) -> float:
        v = raw[key]
        # bool is an int subclass in Python; `fx = true` is a typo, not 1 pixel.
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise NislamError(f"{path}: key '{key}' must be a finite number, got {v!r}")
        return float(v)

    def integer(key: str) -> int:
        v = raw[key]
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise NislamError(f"{path}: key '{key}' must be a positive integer, got {v!r}")
        return v

    def numbers(key: str) -> tuple[float, ...]:
        v = raw[key]
        if not isinstance(v, list) or not all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v
        ):
            raise NislamError(f"{path}: key '{key}' must be a list of finite numbers, got {v!r}")
        return tuple(float(x) for x in v)

    fx, fy, cx, cy = number("fx"), number("fy"), number("cx"), number("cy")
    if fx <= 0 or fy <= 0:
        raise NislamError(f"{path}: key 'fx'/'fy' must be positive, got {fx}, {fy}")
    width, height = integer("width"), integer("height")
    depth_scale = number("depth_scale")
    if depth_scale < 0:
        raise NislamError(
            f"{path}: key 'depth_scale' must be >= 0 (0 = no depth), got {depth_scale}"
        )
    distortion: tuple[float, ...] = ()
    if "distortion" in raw:
        distortion = numbers("distortion")
        if len(distortion) not in _DISTORTION_LENGTHS:
            raise NislamError(
                f"{path}: key 'distortion' needs 4, 5, 8, 12 or 14 OpenCV coefficients, "
                f"got {len(distortion)}"
            )
    q = _IDENTITY_Q_XYZW
    if "q_B_C_xyzw" in raw:
        qv = numbers("q_B_C_xyzw")
        norm = math.sqrt(sum(c * c for c in qv)) if len(qv) == 4 else 0.0
        if len(qv) != 4 or norm < 1e-6:
            raise NislamError(f"{path}: key 'q_B_C_xyzw' must be 4 numbers of non-zero norm")
        q = tuple(c / norm for c in qv)  # type: ignore[assignment]
    return CameraModel(fx, fy, cx, cy, width, height, depth_scale, distortion, q)


# --------------------------------------------------------------------------- lists


def read_file_list(path: Path | str) -> tuple[list[tuple[float, str]], int]:
    """Parse a TUM `timestamp filename` list. Returns (entries, malformed):
    comments and blank lines are ignored; lines with a bad or non-finite
    timestamp or no file name are counted in `malformed` and skipped."""
    entries: list[tuple[float, str]] = []
    malformed = 0
    for line in Path(path).read_text(errors="replace").splitlines():
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        # associate.py accepts ',' and tabs as separators too.
        parts = s.replace(",", " ").replace("\t", " ").split()
        if len(parts) < 2:
            malformed += 1
            continue
        try:
            t_s = float(parts[0])
        except ValueError:
            malformed += 1
            continue
        if not math.isfinite(t_s):
            malformed += 1
            continue
        entries.append((t_s, parts[1]))
    return entries, malformed


def associate(
    rgb_entries: list[tuple[float, str]],
    depth_entries: list[tuple[float, str]],
    max_dt_s: float = DEFAULT_MAX_ASSOC_DT_S,
) -> list[tuple[int, int]]:
    """One-to-one nearest-time pairs (rgb index, depth index), as TUM's
    associate.py: every pair closer than `max_dt_s` is a candidate, candidates
    are taken greedily smallest |dt| first. Sorted by rgb time."""
    if not rgb_entries or not depth_entries:
        return []
    t_rgb = np.array([e[0] for e in rgb_entries], dtype=np.float64)
    t_depth = np.array([e[0] for e in depth_entries], dtype=np.float64)
    order = np.argsort(t_depth, kind="stable")
    t_sorted = t_depth[order]
    # Only depth stamps inside the window can pair, so the candidate set is
    # O(N) instead of associate.py's O(N*M) full product.
    lo = np.searchsorted(t_sorted, t_rgb - max_dt_s, side="left")
    hi = np.searchsorted(t_sorted, t_rgb + max_dt_s, side="right")
    candidates: list[tuple[float, int, int]] = []
    for i in range(len(t_rgb)):
        for k in range(lo[i], hi[i]):
            dt = abs(t_rgb[i] - t_sorted[k])
            if dt < max_dt_s:  # strict, as associate.py
                candidates.append((dt, i, int(order[k])))
    candidates.sort()
    used_rgb: set[int] = set()
    used_depth: set[int] = set()
    pairs: list[tuple[int, int]] = []
    for _dt, i, j in candidates:
        if i in used_rgb or j in used_depth:
            continue
        used_rgb.add(i)
        used_depth.add(j)
        pairs.append((i, j))
    pairs.sort(key=lambda p: (rgb_entries[p[0]][0], p[0]))
    return pairs


def drop_stale_entries(
    entries: list[tuple[float, str]],
) -> tuple[list[tuple[float, str]], int, int]:
    """Keep, in list order, the entries whose stamp is later than every stamp
    kept before them. Returns (kept, duplicates, out_of_order): a repeated stamp
    is a duplicate, an earlier one out of order. Like the onboard loop, which
    drops a stale frame rather than reorder, nothing is moved."""
    kept: list[tuple[float, str]] = []
    duplicates = out_of_order = 0
    last = -math.inf
    for entry in entries:
        if entry[0] > last:
            kept.append(entry)
            last = entry[0]
        elif entry[0] == last:
            duplicates += 1
        else:
            out_of_order += 1
    return kept, duplicates, out_of_order


def stream_gaps(t_s) -> tuple[int, list[tuple[float, float]]]:
    """(dropped frames, clock jumps as (before, after) stamps) of a frame stream.

    A step of CLOCK_JUMP_MIN_S or more is a jump; a shorter step over 1.5
    median intervals has lost round(step / median) - 1 frames. Repeated stamps
    are ignored, so a duplicated or swapped frame is no gap.
    """
    t = np.unique(np.asarray(t_s, dtype=np.float64))
    if len(t) < 3:
        return 0, []
    dt = np.diff(t)
    median = float(np.median(dt))
    jump = dt >= CLOCK_JUMP_MIN_S
    jumps = [(float(t[i]), float(t[i + 1])) for i in np.flatnonzero(jump)]
    gap = ~jump & (dt > _DROP_GAP_FACTOR * median)
    dropped = int(np.sum(np.round(dt[gap] / median) - 1)) if median > 0 else 0
    return dropped, jumps


@dataclass(frozen=True)
class AttitudeFileReport:
    """What `read_attitude_file` skipped or noticed (see SkipCounts)."""

    malformed_lines: int = 0
    nan_samples: int = 0
    spikes: int = 0
    gaps: tuple[tuple[float, float], ...] = ()  # (last sample before, first after)


def read_attitude_file(
    path: Path, max_gap_s: float = DEFAULT_GT_MAX_GAP_S
) -> tuple[Trajectory, AttitudeFileReport]:
    """`timestamp qx qy qz qw` lines -> Trajectory (R_W_B, zero positions).

    Lines that do not parse as five numbers are malformed; rows with a NaN or
    infinite value are NaN samples; isolated jumps are spikes. All three are
    left out. Gaps longer than `max_gap_s` between the remaining samples are
    reported, not filled.
    """
    rows: list[list[float]] = []
    bad = nan = 0
    for line in path.read_text(errors="replace").splitlines():
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        try:
            vals = [float(v) for v in parts]
        except ValueError:
            bad += 1
            continue
        if len(vals) != 5:
            bad += 1
        elif not all(math.isfinite(v) for v in vals):
            nan += 1
        else:
            rows.append(vals)
    a = np.asarray(rows, dtype=np.float64).reshape(-1, 5)
    a = a[np.argsort(a[:, 0], kind="stable")]
    norm = np.linalg.norm(a[:, 1:5], axis=1)
    keep = norm > 1e-6
    keep[1:] &= np.diff(a[:, 0]) > 0
    a, norm = a[keep], norm[keep]
    a[:, 1:5] /= norm[:, None]
    spike = _attitude_spikes(a[:, 1:5])
    a = a[~spike]
    dt = np.diff(a[:, 0])
    gaps = tuple((float(a[i, 0]), float(a[i + 1, 0]))
                 for i in np.flatnonzero(dt > max_gap_s + 1e-9))
    traj = Trajectory.from_samples(a[:, 0], np.zeros((len(a), 3)), a[:, 1:5])
    return traj, AttitudeFileReport(bad, nan, int(spike.sum()), gaps)


def _attitude_spikes(q_xyzw: np.ndarray) -> np.ndarray:
    """Samples more than ATTITUDE_SPIKE_DEG from both neighbours while the
    neighbours agree with each other within it (a jump out and straight back)."""
    n = len(q_xyzw)
    spike = np.zeros(n, dtype=bool)
    if n < 3:
        return spike
    # Rotation angle between unit quaternions a, b: 2 acos(|a . b|).
    cos_half = math.cos(math.radians(ATTITUDE_SPIKE_DEG) / 2.0)
    far_prev = np.abs(np.sum(q_xyzw[1:-1] * q_xyzw[:-2], axis=1)) < cos_half
    far_next = np.abs(np.sum(q_xyzw[1:-1] * q_xyzw[2:], axis=1)) < cos_half
    near_pair = np.abs(np.sum(q_xyzw[:-2] * q_xyzw[2:], axis=1)) >= cos_half
    spike[1:-1] = far_prev & far_next & near_pair
    return spike


# --------------------------------------------------------------------------- images

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SOI = b"\xff\xd8"
_JPEG_EOI = b"\xff\xd9"
_JPEG_TAIL_BYTES = 1024  # some encoders pad after the end-of-image marker


def _png_has_iend(data: bytes) -> bool:
    """Walk the PNG chunk list: complete only if an IEND chunk fits in the data.

    Walking the chunks (a few dozen per frame) is exact, where searching for the
    bytes "IEND" could hit compressed data or miss trailing padding.
    """
    pos = len(_PNG_SIGNATURE)
    while pos + 12 <= len(data):
        (length,) = struct.unpack_from(">I", data, pos)
        end = pos + 12 + length  # length + type + payload + crc
        if end > len(data):
            return False
        if data[pos + 4 : pos + 8] == b"IEND":
            return True
        pos = end
    return False


def _looks_complete(data: bytes) -> bool:
    """False for a PNG without its IEND chunk or a JPEG without its EOI marker.

    OpenCV 4.x builds decode a truncated file partially and only warn (a
    half-grey image would reach the tracker); checking the end cheaply catches
    that whatever the decoder does. Other formats are judged by the decoder.
    """
    if data.startswith(_PNG_SIGNATURE):
        return _png_has_iend(data)
    if data.startswith(_JPEG_SOI):
        return _JPEG_EOI in data[-_JPEG_TAIL_BYTES:]
    return True


def _decode(path: Path, flags: int) -> tuple[np.ndarray | None, str]:
    """Decode an image file; returns (image, "") or (None, reason)."""
    try:
        data = path.read_bytes()
    except OSError as e:
        return None, f"cannot read ({e.strerror})"
    if not data:
        return None, "empty file"
    if not _looks_complete(data):
        return None, "truncated (no end marker)"
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    if img is None:
        return None, "not a decodable image"
    return img, ""


# --------------------------------------------------------------------------- sequence


@dataclass(frozen=True)
class _Pair:
    t_s: float
    rgb_path: Path
    depth_path: Path


@dataclass
class _UndistortMaps:
    """Precomputed remap tables (built once per sequence)."""

    # Fixed-point maps make the bilinear colour remap about twice as fast.
    color_map1: np.ndarray
    color_map2: np.ndarray
    # Float maps for depth: nearest lookup on them rounds to the closest source
    # pixel, while the fixed-point integer part would floor (half-pixel bias).
    depth_map_x: np.ndarray
    depth_map_y: np.ndarray


class Sequence:
    """An opened TUM-layout sequence; iterate it for undistorted RgbdFrames.

    Build with `open_sequence`. `frame_times_s` lists associated frames whose
    two files exist; a frame whose file then fails to decode is skipped during
    iteration (counted in `skipped.unreadable_files`), and so is a frame whose
    depth image holds no measurement (`skipped.empty_depth_frames`).
    """

    def __init__(
        self,
        path: Path,
        camera: CameraModel,
        pairs: list[_Pair],
        groundtruth: Trajectory | None,
        attitude: Trajectory | None,
        skipped: SkipCounts,
        n_rgb_entries: int,
        n_depth_entries: int,
        undistort: bool,
    ) -> None:
        self.path = path
        self.camera = camera
        self.groundtruth = groundtruth
        self.attitude = attitude
        self.skipped = skipped
        self.n_rgb_entries = n_rgb_entries
        self.n_depth_entries = n_depth_entries
        self._pairs = pairs
        self.frame_times_s = np.array([p.t_s for p in pairs], dtype=np.float64)
        # Undistort onto the SAME K (newCameraMatrix = K, not getOptimalNewCameraMatrix):
        # the yielded images then obey the published intrinsics exactly, so configs,
        # papers' numbers and other tools agree; the price is a thin black (depth 0 =
        # invalid) border where the distorted image has no pixels, which trackers
        # already treat as no measurement.
        self.intrinsics = camera.intrinsics()
        self._maps = _build_maps(camera) if (undistort and camera.is_distorted) else None
        self._unreadable: set[Path] = set()
        self._truncated: set[Path] = set()
        self._empty_depth: set[Path] = set()

    def __len__(self) -> int:
        return len(self._pairs)

    def __iter__(self) -> Iterator[RgbdFrame]:
        return self.frames()

    def frames(self) -> Iterator[RgbdFrame]:
        """Yield frames in time order; one summary warning at the end if any
        frame could not be used."""
        dropped = 0
        for i in range(len(self._pairs)):
            frame = self.read_frame(i)
            if frame is None:
                dropped += 1
            else:
                yield frame
        if dropped:
            log.warning(
                "%s: %d of %d frames skipped as unreadable or without depth; totals: %s",
                self.path, dropped, len(self._pairs), self.skipped.summary(),
            )

    def read_frame(self, index: int) -> RgbdFrame | None:
        """Decode and undistort frame `index`; None (and counted) if a file is
        unreadable or the depth image is all zero."""
        pair = self._pairs[index]
        bgr = self._read_color(pair.rgb_path)
        depth_raw = self._read_depth(pair.depth_path) if bgr is not None else None
        if bgr is None or depth_raw is None:
            return None
        if not depth_raw.any():
            # A sensor fault (or a wall inside the minimum range): no measurement
            # at all, so nothing a tracker could use.
            self._empty_depth.add(pair.depth_path)
            self.skipped.empty_depth_frames = len(self._empty_depth)
            log.debug("%s: skipping %s: depth image is all zero", self.path, pair.depth_path.name)
            return None
        if self._maps is not None:
            m = self._maps
            bgr = cv2.remap(bgr, m.color_map1, m.color_map2, cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            # Nearest, not linear: blending across a depth edge invents surfaces.
            depth_raw = cv2.remap(depth_raw, m.depth_map_x, m.depth_map_y, cv2.INTER_NEAREST,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        depth_m = depth_raw.astype(np.float32) / np.float32(self.camera.depth_scale)
        return RgbdFrame(t_s=pair.t_s, bgr=bgr, depth_m=depth_m)

    def load_all(self, max_frames: int | None = None) -> list[RgbdFrame]:
        """Decode up to `max_frames` frames into memory (benchmarks)."""
        out: list[RgbdFrame] = []
        for frame in self.frames():
            if max_frames is not None and len(out) >= max_frames:
                break
            out.append(frame)
        return out

    def groundtruth_at(
        self, t_s, max_gap_s: float = DEFAULT_GT_MAX_GAP_S
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ground-truth (p_xyz_m (M,3), q_xyzw (M,4), valid (M,)) at `t_s`:
        interpolated across gaps up to `max_gap_s`, never extrapolated; invalid rows NaN."""
        if self.groundtruth is None:
            raise NislamError(f"{self.path} has no groundtruth.txt")
        return self.groundtruth.interpolate(t_s, max_gap_s)

    # -- decoding helpers

    def _unreadable_file(self, path: Path, reason: str) -> None:
        if path not in self._unreadable:
            self._unreadable.add(path)
            self.skipped.unreadable_files = len(self._unreadable)
            if reason.startswith("truncated"):
                self._truncated.add(path)
                self.skipped.truncated_files = len(self._truncated)
        log.debug("%s: skipping %s: %s", self.path, path.name, reason)

    def _read_color(self, path: Path) -> np.ndarray | None:
        img, reason = _decode(path, cv2.IMREAD_COLOR)
        shape = (self.camera.height, self.camera.width, 3)
        if img is not None and (img.dtype != np.uint8 or img.shape != shape):
            img, reason = None, f"colour image is {img.dtype} {img.shape}, expected uint8 {shape}"
        if img is None:
            self._unreadable_file(path, reason)
        return img

    def _read_depth(self, path: Path) -> np.ndarray | None:
        img, reason = _decode(path, cv2.IMREAD_UNCHANGED)
        shape = (self.camera.height, self.camera.width)
        if img is not None and (img.dtype != np.uint16 or img.shape != shape):
            img, reason = None, f"depth image is {img.dtype} {img.shape}, expected uint16 {shape}"
        if img is None:
            self._unreadable_file(path, reason)
        return img


def _build_maps(camera: CameraModel) -> _UndistortMaps:
    k = camera.k_matrix()
    dist = np.asarray(camera.distortion, dtype=np.float64)
    size = (camera.width, camera.height)
    c1, c2 = cv2.initUndistortRectifyMap(k, dist, None, k, size, cv2.CV_16SC2)
    dx, dy = cv2.initUndistortRectifyMap(k, dist, None, k, size, cv2.CV_32FC1)
    return _UndistortMaps(c1, c2, dx, dy)


def open_sequence(
    seq_dir: Path | str,
    max_assoc_dt_s: float = DEFAULT_MAX_ASSOC_DT_S,
    undistort: bool = True,
) -> Sequence:
    """Open a TUM-layout sequence folder: camera, lists, association, existence
    checks, ground truth and attitude. Raises NislamError if nothing usable."""
    seq_dir = Path(seq_dir)
    if not seq_dir.is_dir():
        raise NislamError(f"sequence folder {seq_dir} does not exist")
    for name in ("rgb.txt", "depth.txt"):
        if not (seq_dir / name).is_file():
            raise NislamError(f"{seq_dir} has no {name}: not a TUM-layout RGB-D sequence")
    camera = load_camera(seq_dir)
    if camera.depth_scale <= 0:
        raise NislamError(f"{seq_dir}: camera depth_scale is 0 (no depth); replay needs RGB-D")

    skipped = SkipCounts()
    rgb, bad_rgb = read_file_list(seq_dir / "rgb.txt")
    depth, bad_depth = read_file_list(seq_dir / "depth.txt")
    skipped.malformed_lines = bad_rgb + bad_depth
    # Gaps are judged on every colour stamp listed (a stale entry still is a
    # frame the camera took), before stale entries are dropped.
    skipped.dropped_frames, jumps = stream_gaps([t for t, _f in rgb])
    skipped.clock_jumps = len(jumps)
    rgb, dup_rgb, ooo_rgb = drop_stale_entries(rgb)
    depth, dup_depth, ooo_depth = drop_stale_entries(depth)
    skipped.duplicate_stamps = dup_rgb + dup_depth
    skipped.out_of_order_stamps = ooo_rgb + ooo_depth

    # Associate on the full lists first, then drop pairs with a missing file:
    # pairing only the files that survived could marry a colour frame to the
    # wrong depth frame when its true partner is the one that was lost.
    pairs_idx = associate(rgb, depth, max_assoc_dt_s)
    skipped.unassociated = len(rgb) + len(depth) - 2 * len(pairs_idx)

    rgb_exists = [os.path.exists(seq_dir / f) for _t, f in rgb]
    depth_exists = [os.path.exists(seq_dir / f) for _t, f in depth]
    skipped.missing_files = rgb_exists.count(False) + depth_exists.count(False)
    if skipped.missing_files:
        missing = [f for (_t, f), ok in zip(rgb + depth, rgb_exists + depth_exists) if not ok]
        log.debug("%s: %d listed files missing, e.g. %s", seq_dir, len(missing), missing[:5])
    pairs = [
        _Pair(rgb[i][0], seq_dir / rgb[i][1], seq_dir / depth[j][1])
        for i, j in pairs_idx
        if rgb_exists[i] and depth_exists[j]
    ]
    if not pairs:
        raise NislamError(
            f"{seq_dir}: no usable frames ({len(rgb)} rgb / {len(depth)} depth entries, "
            f"{len(pairs_idx)} associated within {max_assoc_dt_s * 1e3:.0f} ms, "
            f"{skipped.missing_files} listed files missing)"
        )

    groundtruth = None
    gt_path = seq_dir / "groundtruth.txt"
    if gt_path.is_file():
        groundtruth, bad = parse_tum_lines(gt_path.read_text(errors="replace").splitlines())
        skipped.malformed_lines += bad
        if len(groundtruth) == 0:
            log.warning("%s: groundtruth.txt holds no valid pose; ignoring it", seq_dir)
            groundtruth = None
    attitude = None
    att_path = seq_dir / "attitude.txt"
    if att_path.is_file():
        attitude, report = read_attitude_file(att_path)
        skipped.malformed_lines += report.malformed_lines
        skipped.attitude_nan_samples = report.nan_samples
        skipped.attitude_spikes = report.spikes
        # A clock jump steps the attitude stamps too; that gap is the jump's.
        skipped.attitude_gaps = sum(
            1 for a0, a1 in report.gaps if not any(a0 < j1 and j0 < a1 for j0, j1 in jumps)
        )
        if len(attitude) == 0:
            log.warning("%s: attitude.txt holds no valid sample; ignoring it", seq_dir)
            attitude = None

    if skipped.total or skipped.noticed:
        # One line for the whole listing; per-file details are at debug level.
        # Unpaired entries alone are normal in TUM recordings (colour and depth
        # streams are not synchronised), so they do not deserve a warning; nor
        # do the few frames a Kinect-class camera drops now and then.
        damaged = (skipped.total - skipped.unassociated + skipped.clock_jumps
                   + skipped.attitude_gaps)
        log.log(logging.WARNING if damaged else logging.INFO,
                "%s: %d usable frames; skipped while listing: %s",
                seq_dir, len(pairs), skipped.summary())
    log.debug("%s: %d rgb / %d depth entries, %d usable frames",
              seq_dir, len(rgb), len(depth), len(pairs))
    return Sequence(seq_dir, camera, pairs, groundtruth, attitude, skipped,
                    len(rgb), len(depth), undistort)
