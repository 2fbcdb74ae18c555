"""NI-SLAM and FastORB in one loop, their motions fused with the AHRS attitude.

The two trackers fail in opposite places (NI-SLAM where the axonometric view
collapses, e.g. along a corridor; FastORB under fast turns and blur), so
`FusedTracker` runs both on every frame and feeds what each measures into one
filter (onboard.fusion.filter.AnchoredFilter): position and velocity in the
AHRS world W, one anchor per tracker. The attitude is the AHRS's (as NI-SLAM
uses it); FastORB's own rotation only orients its motion between anchors.

Per frame:
  1. both trackers track the frame (each in its own world);
  2. the filter predicts to the frame time;
  3. each tracker with a trusted pose measures its motion since its anchor,
     z_i = R_i (p_i - p_i(anchor)), R_i = R_W_C(AHRS) R_i_C^T at the anchor
     (identity for NI-SLAM, whose rotation is the AHRS's), with a covariance
     from its quality signals (onboard.fusion.measurements);
  4. gate: a measurement whose squared Mahalanobis distance to the
     prediction exceeds `gate_chi2` is left out, unless both trackers fail it
     and agree with each other (then the prediction was wrong, not they);
  5. update with the rest; a tracker that made a new key drifts from there
     (its anchor's covariance grows by its pose covariance); one that restarted
     (its reset_counter moved), that comes back after a lost spell, or that
     the gate left out `rejoin_after_frames` frames in a row is re-anchored:
     its anchor becomes the fused position, so it is tied back into the
     fused world without moving the output.

The output is the filter's position with its covariance (reported as
`pose_var`, hence the ODOMETRY covariance) and the AHRS attitude. While at
least one tracker tracks there is no reset; with neither, the filter coasts
for `max_coast_s`, then the result is lost, and the pose after that spell
bumps `reset_counter` once. Which trackers contributed and why another was
left out travel in `TrackResult.contributors` / `left_out`, and are counted
for metrics.json (`stats()`).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from onboard.core.messages import AttitudeSource, KeyframeCloud, RgbdFrame, Tracker, TrackResult, TrackState
from onboard.core.rotations import so3_log
from onboard.fusion.filter import AnchoredFilter
from onboard.fusion.measurements import COVARIANCE_MODELS
from onboard.fusion.params import FusionParams

log = logging.getLogger(__name__)

AHRS_ROT_VAR = 2.0 * 4.592449e-6  # rad^2, as NI-SLAM reports for the AHRS attitude (ref. §10)
GATED = "disagrees (gate)"


def fusion_text(r: TrackResult) -> str:
    """One line for health and status: which trackers the fused pose used
    and why another was left out, e.g. "fastorb only; nislam: lost: too few
    depth pixels"."""
    used = "+".join(r.contributors) if r.contributors else "no tracker"
    if len(r.contributors) == 1:
        used += " only"
    return "; ".join([used, *(f"{name}: {why}" for name, why in r.left_out)])


@dataclass
class _Link:
    """One tracker tied into the fused world through its anchor."""

    index: int
    tracker: Tracker
    anchored: bool = False
    key_id: int = -1
    resets: int = 0
    p_anchor: np.ndarray = field(default_factory=lambda: np.zeros(3))
    R_map: np.ndarray = field(default_factory=lambda: np.eye(3))  # its world's axes in W
    gated_run: int = 0  # frames in a row the gate left it out
    fresh: str | None = None  # back from a lost spell or a restart: why (until measured again)
    used: int = 0
    left_out: collections.Counter = field(default_factory=collections.Counter)
    reanchors: collections.Counter = field(default_factory=collections.Counter)
    nis_sum: float = 0.0
    nis_n: int = 0

    @property
    def name(self) -> str:
        return self.tracker.name

    def to_world(self, p: np.ndarray, R: np.ndarray, anchor_W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A pose in the tracker's world, in W (through the anchor)."""
        return anchor_W + self.R_map @ (p - self.p_anchor), self.R_map @ R


class FusedTracker:
    """`trackers` (NI-SLAM first: its key-frame clouds make the map) fused
    with the AHRS attitude (see the module docstring)."""

    name = "fused"

    def __init__(self, trackers: list[Tracker], params: FusionParams = FusionParams()) -> None:
        self.p = params
        self.links = [_Link(i, t) for i, t in enumerate(trackers)]
        self.filter = AnchoredFilter(len(trackers), params.accel_sd_m_s2)
        self._started = False
        self._lost = False
        self._last_update_s: float | None = None
        self._R_W_C: np.ndarray | None = None
        self.reset_counter = 0
        self.frames = 0
        self.coasted = 0
        self.last_part_ms: dict[str, float] = {}

    # ------------------------------------------------------------------ API
    def track(self, frame: RgbdFrame, attitude: AttitudeSource) -> TrackResult:
        results = []
        for link in self.links:
            t0 = time.perf_counter()
            results.append(link.tracker.track(frame, attitude))
            self.last_part_ms[link.name] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        out = self._fuse(frame.t_s, results, attitude)
        self.last_part_ms["fusion"] = (time.perf_counter() - t0) * 1e3
        self.frames += 1
        return out

    def finish_frame(self) -> None:
        """Each tracker's work for the next frames, after the pose went out."""
        for link in self.links:
            done = getattr(link.tracker, "finish_frame", None)
            if done is not None:
                done()

    def finish(self) -> KeyframeCloud | None:
        cloud = self.links[0].tracker.finish()
        return None if cloud is None else self._cloud_into_world(cloud)

    def stats(self) -> dict[str, object]:
        """What metrics.json reports about the fusion."""
        per = {}
        for link in self.links:
            per[link.name] = {
                "frames_used": link.used,
                "left_out": dict(link.left_out),
                "reanchored": dict(link.reanchors),
                "nis_mean": link.nis_sum / link.nis_n if link.nis_n else None,
            }
        return {"frames": self.frames, "frames_coasted": self.coasted, "trackers": per}

    # ------------------------------------------------------------- fusion
    def _fuse(self, t_s: float, results: list[TrackResult], attitude: AttitudeSource) -> TrackResult:
        offset = results[0].attitude_offset_s
        R_att = attitude.rotation_at(t_s + offset)
        if R_att is not None and not np.all(np.isfinite(R_att)):
            R_att = None
        left_out: list[tuple[str, str]] = []
        trusted = [r.trusted and r.p_W_m is not None and r.R_W_C is not None for r in results]

        if not self._started or self._lost:
            if not any(trusted):
                return self._unposed(t_s, results, "no tracker has a pose")
            self._begin(t_s, results, trusted)
        else:
            self.filter.predict(t_s)

        measured: list[tuple[_Link, TrackResult, np.ndarray, np.ndarray, float]] = []
        to_anchor: list[tuple[_Link, TrackResult, str | None]] = []
        for link, r, ok in zip(self.links, results, trusted):
            if not ok:
                reason = f"lost: {r.lost_reason or 'untrusted'}"
                link.left_out[reason] += 1
                left_out.append((link.name, reason))
                link.fresh = link.fresh or "back after lost"
                continue
            if not link.anchored:
                to_anchor.append((link, r, "joined"))
                continue
            if r.reset_counter != link.resets:
                # Re-localised into its map, or a new map: where it stands in
                # its world is now known only to `rejoin_sd_m` (its map is
                # off by different amounts in different places), so it is
                # measured against its anchor loosened by that much.
                link.resets = r.reset_counter
                link.fresh = "restarted"
                self.filter.diffuse(link.index, np.eye(3) * self.p.rejoin_sd_m**2)
            R = COVARIANCE_MODELS.get(link.name, COVARIANCE_MODELS["fastorb"])(r, self.p)
            if not np.all(np.isfinite(R)):
                link.left_out["no covariance"] += 1
                left_out.append((link.name, "no covariance"))
                continue
            z = link.R_map @ (r.p_W_m - link.p_anchor)
            measured.append((link, r, z, R, self.filter.nis(link.index, z, R)))

        for link, r, z, R, nis in measured:
            self._follow_axes(link, r, R_att)
        accepted, gated = self._gate(measured)
        for link, r, z, R, nis in accepted:
            self.filter.update(link.index, z, R)
            link.used += 1
            link.gated_run = 0
            link.fresh = None  # back in the world it had: its anchor holds
            link.nis_sum += nis
            link.nis_n += 1
        for link, r, z, R, nis in gated:
            # Back from a restart or a lost spell in a world of its own (a new
            # map, a restart at a stale position): tied back in at once.
            why = link.fresh or GATED
            link.gated_run += 1
            link.left_out[why] += 1
            left_out.append((link.name, f"{why}, chi2 {nis:.0f}"))
            log.debug("t=%.3f: %s left out (%s), chi2 %.1f", t_s, link.name, why, nis)
            if link.fresh is not None or link.gated_run >= self.p.rejoin_after_frames:
                to_anchor.append((link, r, link.fresh or "disagreed"))
        # A new key: the tracker's world drifts from here by the error of the
        # pose the key was made at (filter docstring).
        for link, r, z, R, nis in accepted + gated:
            if r.keyframe_id != link.key_id and not r.keyframe_reused:
                self.filter.diffuse(link.index, R * self.p.key_drift_scale)
            link.key_id = r.keyframe_id
        for link, r, why in to_anchor:
            self._anchor(link, r, R_att, why)

        if accepted:
            self._last_update_s = t_s
        elif not to_anchor:
            assert self._last_update_s is not None
            if t_s - self._last_update_s > self.p.max_coast_s:
                self._lost = True
                return self._unposed(t_s, results, "no tracker for "
                                     f"{t_s - self._last_update_s:.2f} s", left_out)
            self.coasted += 1
        contributors = tuple(link.name for link, *_ in accepted)
        tied = [r for _, r, _ in to_anchor]
        return self._result(t_s, results, R_att, accepted, tied, contributors, tuple(left_out))

    def _gate(self, measured: list) -> tuple[list, list]:
        """(accepted, left out) by the chi-square gate (module docstring, step 4)."""
        g = self.p.gate_chi2
        ok = [m for m in measured if m[4] <= g]
        bad = [m for m in measured if m[4] > g]
        if len(bad) == 2 and not ok and self._agree(bad[0], bad[1]):
            return bad, []
        return ok, bad

    def _agree(self, m1: tuple, m2: tuple) -> bool:
        """Whether two measurements put the position at the same place: each
        gives p = a_i + z_i; their difference against its covariance."""
        f = self.filter
        s1, s2 = f._sl(m1[0].index), f._sl(m2[0].index)
        d = (f.x[s1] + m1[2]) - (f.x[s2] + m2[2])
        S = f.P[s1, s1] + f.P[s2, s2] - f.P[s1, s2] - f.P[s2, s1] + m1[3] + m2[3]
        return float(d @ np.linalg.solve(S, d)) <= self.p.gate_chi2

    def _begin(self, t_s: float, results: list[TrackResult], trusted: list[bool]) -> None:
        """First pose, or the first after a lost spell: the filter restarts at
        the last position put out (a restart there, as the trackers do)."""
        p0 = self.filter.p if self._started else np.zeros(3)
        if self._started:
            self.reset_counter += 1
            log.info("t=%.3f: fused pose back after a lost spell: reset %d", t_s, self.reset_counter)
        self.filter.start(t_s, p0, 0.0, self.p.initial_speed_sd_m_s)
        self._started, self._lost = True, False
        self._last_update_s = t_s
        for link in self.links:
            link.anchored, link.fresh = False, None

    def _follow_axes(self, link: _Link, r: TrackResult, R_att: np.ndarray | None) -> None:
        """Refine the tracker's axes in W, R_i = mean of R_W_C(AHRS) R_i_C^T: one
        frame's pair is off by the attitude's noise and time offset (a degree
        turns a metre of motion by 1.7 cm), and FastORB's world slowly turns
        against the AHRS. A small step towards this frame's pair each frame
        (`axes_gain`): an exponential mean on SO(3)."""
        if R_att is None or self.p.axes_gain <= 0.0:
            return
        d = so3_log(link.R_map.T @ R_att @ np.asarray(r.R_W_C).T)
        link.R_map = link.R_map @ Rotation.from_rotvec(self.p.axes_gain * d).as_matrix()

    def _anchor(self, link: _Link, r: TrackResult, R_att: np.ndarray | None, why: str | None) -> None:
        self.filter.anchor(link.index)
        link.anchored = True
        link.key_id = r.keyframe_id
        link.resets = r.reset_counter
        link.gated_run = 0
        link.fresh = None
        link.p_anchor = np.asarray(r.p_W_m, dtype=np.float64).copy()
        if R_att is not None:  # without the AHRS the last mapping stays
            link.R_map = R_att @ np.asarray(r.R_W_C).T
        if why is not None:
            link.reanchors[why] += 1
            if why != "joined" or self.frames > 0:
                log.info("%s tied back into the fused world (%s)", link.name, why)

    # ------------------------------------------------------------- results
    def _attitude(self, results: list[TrackResult], R_att: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """R_W_C and its variances: the AHRS's, else a tracker's mapped into W."""
        if R_att is not None:
            return R_att, np.full(3, AHRS_ROT_VAR)
        for link, r in zip(self.links, results):
            if r.trusted and r.R_W_C is not None:
                return link.R_map @ r.R_W_C, np.asarray(r.pose_var[3:], dtype=np.float64)
        assert self._R_W_C is not None
        return self._R_W_C, np.full(3, 10.0 * AHRS_ROT_VAR)

    def _result(self, t_s: float, results: list[TrackResult], R_att: np.ndarray | None,
                accepted: list, tied: list[TrackResult], contributors: tuple[str, ...],
                left_out: tuple[tuple[str, str], ...]) -> TrackResult:
        R_W_C, rot_var = self._attitude(results, R_att) if (
            R_att is not None or self._R_W_C is not None or any(r.trusted for r in results)
        ) else (np.eye(3), np.full(3, 1.0))
        self._R_W_C = R_W_C
        P = self.filter.P_pp
        pose_var = np.concatenate([np.diag(P), rot_var])
        if accepted:  # the motion measured this frame: information of all updates
            info = sum(np.linalg.inv(m[3]) for m in accepted)
            sd = math.sqrt(float(np.trace(np.linalg.inv(info))) / 3.0)
            quality = int(np.clip(round(100.0 * self.p.quality_sd_m / sd), 1, 100))
        elif tied:
            # Only tied in this frame (the first pose, a tracker back): its own say.
            quality = max(r.quality for r in tied)
        else:
            quality = 10  # coasting on the motion model: below the degraded threshold
        head = results[0]
        clouds = tuple(self._cloud_into_world(c) for c in head.finished_keyframes)
        return TrackResult(
            t_s=t_s, state=TrackState.TRACKING, trusted=True, p_W_m=self.filter.p,
            R_W_C=R_W_C, pose_var=pose_var, quality=quality, psr=head.psr,
            keyframe_id=head.keyframe_id, new_keyframe=head.new_keyframe,
            reset_counter=self.reset_counter, lost_reason=None, shift_cells=head.shift_cells,
            tz_m=head.tz_m, res_m=head.res_m, rotation_residual_rad=head.rotation_residual_rad,
            attitude_offset_s=head.attitude_offset_s, matched_cells=head.matched_cells,
            finished_keyframes=clouds, keyframe_reused=head.keyframe_reused,
            contributors=contributors, left_out=left_out,
        )

    def _unposed(self, t_s: float, results: list[TrackResult], reason: str,
                 left_out: list[tuple[str, str]] | None = None) -> TrackResult:
        head = results[0]
        if left_out is None:
            left_out = [(link.name, f"lost: {r.lost_reason or 'untrusted'}")
                        for link, r in zip(self.links, results)]
            for link, (_, why) in zip(self.links, left_out):
                link.left_out[why] += 1
        return dataclasses.replace(
            head, t_s=t_s, state=TrackState.LOST if self._started else TrackState.INITIALIZING,
            trusted=False, p_W_m=None, R_W_C=None, pose_var=np.full(6, np.nan), quality=0,
            reset_counter=self.reset_counter, lost_reason=reason,
            finished_keyframes=tuple(self._cloud_into_world(c) for c in head.finished_keyframes),
            contributors=(), left_out=tuple(left_out),
        )

    def _cloud_into_world(self, cloud: KeyframeCloud) -> KeyframeCloud:
        link = self.links[0]
        a = self.filter.x[self.filter._sl(0)]
        p, R = link.to_world(cloud.p_W_m, cloud.R_W_C, a)
        return dataclasses.replace(cloud, p_W_m=p, R_W_C=R)
