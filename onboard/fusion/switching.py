"""A primary tracker with a fallback for when the attitude is unavailable.

NI-SLAM needs the AHRS for every frame; FastORB needs none. `SwitchingTracker`
runs the primary, and when it reports "no attitude" it starts a fresh
fallback tracker on that same frame; once the attitude has been back for
`return_after_s` it hands over to the primary again. It is a `Tracker`
itself, so the loop never asks which one runs.

One world for the outputs. Each tracker reports poses in its own world; the
first trusted pose after a switch is tied to the last trusted pose before
it, which fixes a rigid transform from that tracker's world into ours:
- the fallback (a fresh FastORB, its world fixed by its first frame): full
  SE(3), T_W_Wf = T_W_C(last) T_Wf_C(first)^-1;
- the primary (NI-SLAM: rotation straight from the AHRS, absolute): a
  translation only, so its attitude stays the AHRS's.
Each switch adds one to `reset_counter` (on top of the trackers' own
resets): the step between the two poses tied together is real motion that
nothing measured, and the flight controller must not fuse it as such.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable

import numpy as np

from onboard.core.messages import AttitudeSource, KeyframeCloud, RgbdFrame, Tracker, TrackResult

log = logging.getLogger(__name__)

NO_ATTITUDE = "no attitude"  # NislamTracker's lost_reason when the AHRS has no sample


@dataclasses.dataclass
class _Frame:
    """A rigid transform from a tracker's world into ours."""

    R: np.ndarray
    t: np.ndarray

    @classmethod
    def identity(cls) -> _Frame:
        return cls(np.eye(3), np.zeros(3))

    def pose(self, p_m: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.R @ p_m + self.t, self.R @ R


class SwitchingTracker:
    """`primary` with `make_fallback()` standing in while the attitude is
    missing (see the module docstring). `fallback_name` None: no fallback."""

    def __init__(
        self,
        primary: Tracker,
        make_fallback: Callable[[], Tracker] | None,
        return_after_s: float = 1.0,
    ) -> None:
        self.primary = primary
        self.make_fallback = make_fallback
        self.return_after_s = return_after_s
        self.name = primary.name
        self.fallback: Tracker | None = None  # the running fallback, if any
        self.switches = 0
        self._frame = _Frame.identity()  # the active tracker's world in ours
        self._tie_rotation: bool | None = None  # a tie is pending: with rotation?
        self._last: tuple[np.ndarray, np.ndarray] | None = None  # last trusted (p_W, R_W_C)
        self._attitude_since_s: float | None = None
        self.reset_counter = 0
        self._own_resets: int | None = None  # the active tracker's counter when last seen
        self.loop_corrections = 0  # ours: the active tracker's loop corrections, summed
        self._own_loops: int | None = None

    @property
    def active_name(self) -> str:
        return self.primary.name if self.fallback is None else self.fallback.name

    @property
    def fallback_active(self) -> bool:
        return self.fallback is not None

    def track(self, frame: RgbdFrame, attitude: AttitudeSource) -> TrackResult:
        if self.fallback is not None and self._attitude_back(frame.t_s, attitude):
            self._switch(to_fallback=False, t_s=frame.t_s)
        if self.fallback is None:
            result = self.primary.track(frame, attitude)
            if result.lost_reason != NO_ATTITUDE or self.make_fallback is None:
                return self._into_world(result)
            self._attitude_since_s = None
            self._switch(to_fallback=True, t_s=frame.t_s)
        assert self.fallback is not None
        return self._into_world(self.fallback.track(frame, attitude))

    def backend_step(self) -> bool:
        """One unit of the active tracker's back-end work (FastORB's local
        mapping), for the loop's idle time; False when it has none."""
        step = getattr(self.fallback or self.primary, "backend_step", None)
        return bool(step()) if step is not None else False

    def finish_frame(self) -> None:
        """The trackers' work for the next frames, after the pose went out."""
        for tracker in (self.primary, self.fallback):
            finish_frame(tracker)

    def finish(self) -> KeyframeCloud | None:
        cloud = (self.fallback or self.primary).finish()
        return None if cloud is None else self._cloud_into_world(cloud)

    # ------------------------------------------------------------ switching
    def _attitude_back(self, t_s: float, attitude: AttitudeSource) -> bool:
        r = attitude.rotation_at(t_s)
        if r is None or not np.all(np.isfinite(r)):
            self._attitude_since_s = None
            return False
        if self._attitude_since_s is None:
            self._attitude_since_s = t_s
        return t_s - self._attitude_since_s >= self.return_after_s

    def _switch(self, to_fallback: bool, t_s: float) -> None:
        if to_fallback:
            assert self.make_fallback is not None
            self.fallback = self.make_fallback()
        else:
            self.fallback = None  # a later switch starts a fresh one: its map is stale
        self.switches += 1
        self.reset_counter += 1
        self._own_resets = None  # the next result sets the new tracker's baseline
        self._own_loops = None
        self._frame = _Frame.identity()
        # Before any trusted pose there is nothing to tie to: keep the tracker's world.
        self._tie_rotation = to_fallback if self._last is not None else None
        log.warning("t=%.3f s: switched to the %s tracker (%s)", t_s, self.active_name,
                    "no attitude" if to_fallback else f"attitude back for {self.return_after_s:g} s")

    # ------------------------------------------------------------ world frames
    def _into_world(self, result: TrackResult) -> TrackResult:
        # Our counter moves with the active tracker's own resets and by one per
        # switch (a tracker's restart right at a switch is that same switch).
        if self._own_resets is not None:
            self.reset_counter += max(0, result.reset_counter - self._own_resets)
        self._own_resets = result.reset_counter
        # Loop corrections likewise: a switch must not read as one (the MAVLink
        # feed announces a change of this counter as a reset).
        if self._own_loops is not None:
            self.loop_corrections += max(0, result.loop_corrections - self._own_loops)
        self._own_loops = result.loop_corrections
        if result.trusted and result.p_W_m is not None and result.R_W_C is not None:
            if self._tie_rotation is not None and self._last is not None:
                self._frame = _tie(self._last, result.p_W_m, result.R_W_C, self._tie_rotation)
                self._tie_rotation = None
            p_W, R_W = self._frame.pose(result.p_W_m, result.R_W_C)
            self._last = (p_W, R_W)
            var = result.pose_var.copy()
            var[:3] = (self._frame.R**2) @ var[:3]
            result = dataclasses.replace(result, p_W_m=p_W, R_W_C=R_W, pose_var=var)
        clouds = tuple(self._cloud_into_world(c) for c in result.finished_keyframes)
        moved = tuple((k, *self._frame.pose(p, R)) for k, p, R in result.moved_keyframes)
        return dataclasses.replace(result, reset_counter=self.reset_counter, finished_keyframes=clouds,
                                   loop_corrections=self.loop_corrections, moved_keyframes=moved)

    def _cloud_into_world(self, cloud: KeyframeCloud) -> KeyframeCloud:
        p, R = self._frame.pose(cloud.p_W_m, cloud.R_W_C)
        return dataclasses.replace(cloud, p_W_m=p, R_W_C=R)


def finish_frame(tracker: object) -> None:
    """`tracker.finish_frame()` when it has deferred work (onboard.nislam.deferred)."""
    done = getattr(tracker, "finish_frame", None)
    if done is not None:
        done()


def _tie(last: tuple[np.ndarray, np.ndarray], p_T: np.ndarray, R_T: np.ndarray,
         with_rotation: bool) -> _Frame:
    """The transform taking the pose (p_T, R_T) in a tracker's world onto
    `last` in ours: full SE(3), or a translation only."""
    p_W, R_W = last
    R = R_W @ R_T.T if with_rotation else np.eye(3)
    return _Frame(R, p_W - R @ p_T)
