"""One tracker as the fused tracker (onboard.fusion.fused) holds it: where it
is tied into the fused world, the keys it may come back to, and its counts."""

from __future__ import annotations

import collections
from dataclasses import dataclass, field

import numpy as np

from onboard.core.messages import Tracker, TrackResult


@dataclass
class Link:
    """One tracker tied into the fused world: the fused position of the point
    it measures its motion from (the anchor, a clone in the filter) and of its
    last frame (a clone too, to promote when the tracker makes a new key)."""

    index: int
    tracker: Tracker
    anchored: bool = False
    anchor_slot: int = -1  # the filter slot of the clone it measures from
    # A tracker that measures against keys: the fused clone of each key it
    # may come back to, id -> (slot, its measurement there, its world position there).
    keys: collections.OrderedDict = field(default_factory=collections.OrderedDict)
    ref: tuple[int, int] = (0, -1)  # (reset counter, reference key) the anchor belongs to
    resets: int = 0
    o: np.ndarray = field(default_factory=lambda: np.zeros(3))  # its measurement at the anchor
    p_anchor: np.ndarray = field(default_factory=lambda: np.zeros(3))  # its world position there
    m_last: np.ndarray = field(default_factory=lambda: np.zeros(3))
    p_last: np.ndarray = field(default_factory=lambda: np.zeros(3))
    R_map: np.ndarray = field(default_factory=lambda: np.eye(3))  # its world's axes in W
    used: int = 0
    left_out: collections.Counter = field(default_factory=collections.Counter)
    reanchors: collections.Counter = field(default_factory=collections.Counter)
    closing: bool = False  # this frame closes a loop (back on a key whose clone is held)
    skipped: bool = False  # its last frame was left out as an outlier, its reference kept
    nis_sum: float = 0.0
    nis_n: int = 0

    @property
    def name(self) -> str:
        return self.tracker.name

    @property
    def last_slot(self) -> int:
        return 2 * self.index + 1

    def to_world(self, p: np.ndarray, R: np.ndarray, anchor_W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A pose in the tracker's world, in W (through the anchor)."""
        return anchor_W + self.R_map @ (p - self.p_anchor), self.R_map @ R


def measured_by(r: TrackResult) -> tuple[np.ndarray, tuple[int, int], bool]:
    """What the tracker measured this frame, the reference it measured it
    against, and whether that is a key (True: the position relative to the
    key, `reference_offset_m`) or its world (False: `p_W_m`)."""
    if r.reference_offset_m is not None and r.reference_keyframe_id >= 0:
        return np.asarray(r.reference_offset_m, dtype=np.float64), (r.reset_counter, r.reference_keyframe_id), True
    return np.asarray(r.p_W_m, dtype=np.float64), (r.reset_counter, r.keyframe_id), False
