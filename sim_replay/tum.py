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
import os
from collections.abc import Iterator
from dataclasses import dataclass, fields
from pathlib import Path

import cv2
import numpy as np

from onboard import NislamError
from onboard.core.camera import CameraModel, undistort_maps
from onboard.core.messages import RgbdFrame
from onboard.core.trajectory import Trajectory, parse_tum_lines
from sim_replay.images import decode_image
from sim_replay.outdir import check_complete
from sim_replay.stamps import DEFAULT_WINDOW_S, StampFit, fit_camera_clock
from sim_replay.tum_files import (
    DEFAULT_GT_MAX_GAP_S,
    DEFAULT_MAX_ASSOC_DT_S,
    associate,
    drop_stale_entries,
    load_camera,
    read_attitude_file,
    read_file_list,
    stream_gaps,
)

log = logging.getLogger(__name__)


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


# --------------------------------------------------------------------------- lists


# --------------------------------------------------------------------------- images


# --------------------------------------------------------------------------- sequence


@dataclass(frozen=True)
class _Pair:
    t_s: float
    rgb_path: Path
    depth_path: Path
    depth_t_s: float | None = None  # the depth image's own stamp


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
        stamps: StampFit | None = None,
    ) -> None:
        self.path = path
        # How the colour stamps became capture times (sim_replay/stamps.py).
        self.stamps = stamps
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
        self._maps = undistort_maps(camera) if (undistort and camera.is_distorted) else None
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
        depth_t_s = None if pair.depth_t_s is None else pair.depth_t_s + self.camera.depth_lag_s
        return RgbdFrame(t_s=pair.t_s, bgr=bgr, depth_m=depth_m, depth_t_s=depth_t_s)

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
        img, reason = decode_image(path, cv2.IMREAD_COLOR)
        shape = (self.camera.height, self.camera.width, 3)
        if img is not None and (img.dtype != np.uint8 or img.shape != shape):
            img, reason = None, f"colour image is {img.dtype} {img.shape}, expected uint8 {shape}"
        if img is None:
            self._unreadable_file(path, reason)
        return img

    def _read_depth(self, path: Path) -> np.ndarray | None:
        img, reason = decode_image(path, cv2.IMREAD_UNCHANGED)
        shape = (self.camera.height, self.camera.width)
        if img is not None and (img.dtype != np.uint16 or img.shape != shape):
            img, reason = None, f"depth image is {img.dtype} {img.shape}, expected uint16 {shape}"
        if img is None:
            self._unreadable_file(path, reason)
        return img


def open_sequence(
    seq_dir: Path | str,
    max_assoc_dt_s: float = DEFAULT_MAX_ASSOC_DT_S,
    undistort: bool = True,
    stamp_window_s: float = DEFAULT_WINDOW_S,
) -> Sequence:
    """Open a TUM-layout sequence folder: camera, lists, association, existence
    checks, ground truth and attitude. Raises NislamError if nothing usable.

    Colour and depth stamps are each fitted to their camera's clock over
    +-`stamp_window_s` (0 = as recorded; sim_replay/stamps.py says why); the
    pairing is done on these capture times."""
    seq_dir = Path(seq_dir)
    if not seq_dir.is_dir():
        raise NislamError(f"sequence folder {seq_dir} does not exist")
    check_complete(seq_dir)
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

    # Pair on capture times: recorded host stamps jitter by 1-2 ms each, and on
    # two free-running clocks (fr1/rpy: 33.336 and 33.369 ms) a pair near half
    # a period apart falls out of the window by its jitter alone (28 of 723
    # frames of fr1/rpy, each leaving a two-frame step in the trajectory).
    rgb_fit = fit_camera_clock([t for t, _f in rgb], stamp_window_s)
    depth_t = fit_camera_clock([t for t, _f in depth], stamp_window_s).t_s
    rgb = [(float(t), f) for t, (_t, f) in zip(rgb_fit.t_s, rgb)]
    depth = [(float(t), f) for t, (_t, f) in zip(depth_t, depth)]
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
        _Pair(rgb[i][0], seq_dir / rgb[i][1], seq_dir / depth[j][1], depth[j][0])
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
    log.debug("%s: %d rgb / %d depth entries, %d usable frames; colour %s",
              seq_dir, len(rgb), len(depth), len(pairs), rgb_fit.describe())
    return Sequence(seq_dir, camera, pairs, groundtruth, attitude, skipped,
                    len(rgb), len(depth), undistort, rgb_fit)
