"""The text files of a TUM-layout recording: the camera (camera.toml or the
published TUM intrinsics), the timestamped file lists and their association,
and attitude.txt. Bad lines are counted, never fatal.
"""

from __future__ import annotations

import bisect
import logging
import math
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from onboard import NislamError
from onboard.core.camera import CameraModel
from onboard.core.rotations import IDENTITY_Q_XYZW
from onboard.core.trajectory import Trajectory

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


_DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)  # what OpenCV accepts


# Published TUM RGB-D colour intrinsics (vision.in.tum.de, "Intrinsic Camera Calibration").
# The TUM sequences come from Kinect-class RGB-D cameras whose colour sensor
# is a rolling shutter; 28 ms from the first row to the last is the readout
# Kerl, Stueckler and Cremers gave the simulated rolling-shutter RGB-D camera
# of their benchmark (ICCV 2015, "Dense Continuous-Time Tracking and Mapping
# with Rolling Shutter RGB-D Cameras"), not a value fitted to these sequences.
_KINECT_READOUT_S = 0.028
# Its depth image is captured before the instant its stamp says: 20 ms, set
# from tum_fr1_rpy the way a rig's clock is calibrated once. With the colour
# shutter modelled and the depth taken at stamp - 20 ms, the attitude offset
# the online calibration settles at falls from -18..-23 ms to -1..-5 ms (TUM
# synchronised the motion capture with the camera's host, so ~0 is the truth),
# the error against a key from 23 to 15 mm; any lag from -15 to -30 ms gives
# about the same (docs/nislam-error-budget.md, "The depth's own clock").
_KINECT_DEPTH_LAG_S = -0.020
_TUM_CAMERAS: dict[int, CameraModel] = {
    1: CameraModel(517.3, 516.5, 318.6, 255.3, 640, 480, 5000.0,
                   (0.2624, -0.9531, -0.0054, 0.0026, 1.1633), readout_s=_KINECT_READOUT_S,
                   depth_lag_s=_KINECT_DEPTH_LAG_S),
    2: CameraModel(520.9, 521.0, 325.1, 249.7, 640, 480, 5000.0,
                   (0.2312, -0.7849, -0.0033, -0.0001, 0.9172), readout_s=_KINECT_READOUT_S,
                   depth_lag_s=_KINECT_DEPTH_LAG_S),
    3: CameraModel(535.4, 539.2, 320.1, 247.6, 640, 480, 5000.0, (),
                   readout_s=_KINECT_READOUT_S, depth_lag_s=_KINECT_DEPTH_LAG_S),
}


# "fr1", "fr_1", "freiburg1" ... but not "fr12" or "frame1".
_TUM_NAME_RE = re.compile(r"(?:freiburg|fr)_?([123])(?!\d)")


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

    known = {"fx", "fy", "cx", "cy", "width", "height", "depth_scale", "distortion", "q_B_C_xyzw",
             "readout_s", "depth_lag_s"}
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
    q = IDENTITY_Q_XYZW
    if "q_B_C_xyzw" in raw:
        qv = numbers("q_B_C_xyzw")
        norm = math.sqrt(sum(c * c for c in qv)) if len(qv) == 4 else 0.0
        if len(qv) != 4 or norm < 1e-6:
            raise NislamError(f"{path}: key 'q_B_C_xyzw' must be 4 numbers of non-zero norm")
        q = tuple(c / norm for c in qv)  # type: ignore[assignment]
    readout = number("readout_s") if "readout_s" in raw else 0.0
    if not 0.0 <= readout <= 0.1:
        raise NislamError(
            f"{path}: key 'readout_s' must be 0 (global shutter) to 0.1 s, got {readout}")
    depth_lag = number("depth_lag_s") if "depth_lag_s" in raw else 0.0
    if not -0.1 <= depth_lag <= 0.1:
        raise NislamError(f"{path}: key 'depth_lag_s' must be -0.1 to 0.1 s, got {depth_lag}")
    return CameraModel(fx, fy, cx, cy, width, height, depth_scale, distortion, q, readout,
                       depth_lag)


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
    """Keep, in list order, the longest run of entries whose stamps rise
    (the longest strictly increasing subsequence; of equally long ones, the
    one taking the earliest lines). Returns (kept, duplicates, out_of_order):
    a left-out entry whose stamp repeats a kept one is a duplicate, any other
    is out of order. Nothing is moved, as the onboard loop drops a stale frame
    rather than reorder; but one bad line whose stamp runs ahead (a garbage
    line, a clock glitch) costs that line only, not every good frame stamped
    before it, as a "later than everything kept so far" rule would."""
    n = len(entries)
    t = [e[0] for e in entries]
    # longest[i]: length of the longest rising run starting at entry i. Built
    # right to left: a rising run from i is a falling run of -t ending at i in
    # reversed order, found by patience sorting (O(n log n)).
    longest = [0] * n
    tails: list[float] = []
    for i in range(n - 1, -1, -1):
        k = bisect.bisect_left(tails, -t[i])
        if k == len(tails):
            tails.append(-t[i])
        else:
            tails[k] = -t[i]
        longest[i] = k + 1
    keep = [False] * n
    need = len(tails)
    last = -math.inf
    for i in range(n):  # the earliest entry that can still start a run of `need`
        if need and t[i] > last and longest[i] == need:
            keep[i] = True
            last = t[i]
            need -= 1
    kept = [e for e, k in zip(entries, keep) if k]
    kept_stamps = {e[0] for e in kept}
    duplicates = sum(1 for e, k in zip(entries, keep) if not k and e[0] in kept_stamps)
    return kept, duplicates, n - len(kept) - duplicates


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
