"""A frame's match against one key (projection, response, peak, depth
translation: Eqs. 14-18 without the tracker's bookkeeping), and the same
matches started early on a spare core.

A frame whose match against its key weakens below T_r is matched against the
kept keys before its pose (NislamTracker._reuse): two or three matches in
series, the slowest 1 % of frames and so the latency's p99 (docs/latency.md).
The PSR falls gradually as the view leaves a key (on `circle` each weakened
match came after a frame within 1.16 T_r), so when the last frame's PSR is
within `speculate_psr_ratio` T_r the kept keys' matches start on a spare core
while the loop matches the current key; a re-use then takes the finished one.
Each is a pure function of the frame's cloud, the key and the search window:
one started with other inputs than the re-use would use is not taken, so the
poses are those of the matches done in series, bit for bit.
"""

from __future__ import annotations

import logging
from concurrent.futures import Executor, Future, wait
from dataclasses import dataclass

import numpy as np

from onboard.core.messages import AttitudeSource
from onboard.nislam.correlation import Peak, find_peak, whiten
from onboard.nislam.depth import DepthFit, depth_translation
from onboard.nislam.keys import Key
from onboard.nislam.params import NislamParams
from onboard.nislam.projection import AxonometricImage, Cloud, project

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Window:
    """Where a key's match looks: the rotation into its axes and the search window."""

    r_rel: np.ndarray  # R_key^-1 R_cur
    centre_cells: tuple[float, float]
    radius_cells: int

    def same(self, other: Window) -> bool:
        return (np.array_equal(self.r_rel, other.r_rel) and self.centre_cells == other.centre_cells
                and self.radius_cells == other.radius_cells)


@dataclass(frozen=True)
class Raw:
    """A match before the tracker books it (None parts: it failed there)."""

    img: AxonometricImage
    covered: float
    peak: Peak | None = None
    depth: DepthFit | None = None

    @property
    def ok(self) -> bool:
        return self.depth is not None


def search_window(key: Key, t_s: float, r_rel: np.ndarray, p: NislamParams,
                  fresh: bool = False) -> Window:
    """The window grows with the time since the key's last match, so a stalled
    loop or dropped frames widen it instead of losing the key; `fresh`: the
    key's motion prior is stale (a kept key: search it all)."""
    if fresh:
        centre, since_s = (0.0, 0.0), t_s - key.t_s
    else:
        centre, since_s = key.predicted_shift(t_s), key.since_last_match_s(t_s)
    radius_m = max(p.search_radius_m, p.search_speed_m_s * since_s)
    return Window(r_rel, centre, max(3, int(radius_m / key.img.res_m)))


def measure(key: Key, cloud: Cloud, win: Window, shape: tuple[int, int],
            front: tuple[float, float], p: NislamParams) -> Raw:
    """Project the cloud into the key's axes (Sec. IV-A), correlate (Eq. 14),
    find the peak and its PSR (Eqs. 15-16), translate in depth (Eq. 18)."""
    img = project(cloud, win.r_rel, shape, key.img.res_m, front=front)
    covered = float(img.mask.mean())
    if covered < p.min_valid_fraction:
        return Raw(img, covered)
    peak = find_peak(key.filt.response(whiten(img.gray, img.mask)), p.psr_exclude_cells,
                     win.centre_cells, win.radius_cells, p.peak_lobe_centroid)
    if not peak.psr >= p.psr_lost:  # also catches NaN
        return Raw(img, covered, peak)
    du, dv = int(round(peak.du_cells)), int(round(peak.dv_cells))
    depth = depth_translation(key, img, du, dv, p, (peak.du_cells - du, peak.dv_cells - dv))
    return Raw(img, covered, peak, depth)


class Speculation:
    """Matches of one frame started on a spare core, by key id."""

    def __init__(self, spare: Executor) -> None:
        self._spare = spare
        self._started: dict[int, tuple[Window, Future[Raw]]] = {}

    def start(self, cands: list[Key], cloud: Cloud, t_s: float, r_cur: np.ndarray,
              attitude: AttitudeSource, offset_s: float, shape: tuple[int, int],
              front: tuple[float, float], p: NislamParams) -> None:
        """Match the frame against each of `cands` as a re-use would: the
        key's attitude looked up at the current offset, its prior stale."""
        for key in cands:
            r_key = attitude.rotation_at(key.t_s + offset_s)
            r_key = key.R_W_C if r_key is None else r_key
            win = search_window(key, t_s, r_key.T @ r_cur, p, fresh=True)
            fut = self._spare.submit(measure, key, cloud, win, shape, front, p)
            self._started[key.keyframe_id] = (win, fut)

    def take(self, key: Key, win: Window) -> Raw | None:
        """The match of `key` started with the same window (waits for it), else None."""
        got = self._started.get(key.keyframe_id)
        if got is None or not got[0].same(win):
            return None
        return got[1].result()

    def settle(self) -> None:
        """Wait for every match still running: before anything moves or
        overwrites a key (a new key may take a kept key's memory)."""
        started, self._started = self._started, {}
        wait([fut for _, fut in started.values()])
        for key_id, (_, fut) in started.items():
            if fut.exception() is not None:  # a match in series would have raised it
                log.warning("a match of key %d started early failed: %s", key_id, fut.exception())
