"""NI-SLAM and FastORB in one loop, their motions fused with the AHRS attitude.

The two trackers fail in opposite places (NI-SLAM where the axonometric view
collapses, e.g. along a corridor; FastORB under fast turns and blur), so
`FusedTracker` runs both on every frame and feeds what each measures into one
filter (onboard.fusion.filter.AnchoredFilter): position and velocity in the
AHRS world W, one anchor per tracker. The attitude is the AHRS's (as NI-SLAM
uses it); FastORB's own rotation only orients its motion between anchors.

Each tracker is used for what it measures, never for a jump inside its own
world (docs/fusion.md, "Discontinuities"):
  - NI-SLAM tells its position relative to the key it matched
    (`reference_offset_m`). The filter keeps a clone of each key's fused
    position (made from the fused position of the frame the key was made at)
    and measures z = R_i d = p - a_key: motion within a key, and across a new
    key motion from that frame, so a key inherits the fused error, not
    NI-SLAM's. When NI-SLAM re-uses a kept key whose clone is still held, the
    same measurement against that old clone closes the loop (the drift since
    comes out with the covariance the filter carried); without a clone, or
    after a restart, the frame only ties it back in.
  - FastORB tells its position in its map's world: motion since the fused
    position at its last key; a re-localisation or a new map (its
    reset_counter moved) only ties it back in.

Per frame:
  1. both trackers track the frame (each in its own world);
  2. the filter predicts to the frame time;
  3. each tracker with a trusted pose measures its motion as above, rotated
     into W (R_i = R_W_C(AHRS) R_i_C^T, followed slowly), with a covariance
     from its quality signals (onboard.fusion.measurements);
  4. gate: a measurement whose squared Mahalanobis distance to the
     prediction exceeds `gate_chi2` is left out, unless both trackers fail it
     and agree with each other (then the prediction was wrong, not they);
  5. update with the rest; a tracker left out, restarted or back in a world
     of its own is tied in at this frame (its anchor becomes the fused
     position), so the output does not move.

The output is the filter's position with its covariance (reported as
`pose_var`, hence the ODOMETRY covariance) and the AHRS attitude. While at
least one tracker tracks there is no reset; with neither, the filter coasts
for `max_coast_s`, then the result is lost, and the pose after that spell
bumps `reset_counter` once. Which trackers contributed and why another was
left out travel in `TrackResult.contributors` / `left_out`, and are counted
for metrics.json (`stats()`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time

import numpy as np
from scipy.spatial.transform import Rotation

from onboard.core.attitude_smoothing import without_widening
from onboard.core.messages import AttitudeSource, KeyframeCloud, RgbdFrame, Tracker, TrackResult, TrackState
from onboard.core.rotations import so3_log
from onboard.fusion.agreement import OutlierCheck
from onboard.fusion.displacement import OutputClones
from onboard.fusion.filter import AnchoredFilter
from onboard.fusion.links import Link, measured_by
from onboard.fusion.measurements import COVARIANCE_MODELS, key_attitude_cov
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


class FusedTracker:
    """`trackers` (NI-SLAM first: its key-frame clouds make the map) fused
    with the AHRS attitude (see the module docstring)."""

    name = "fused"

    def __init__(self, trackers: list[Tracker], params: FusionParams = FusionParams()) -> None:
        self.p = params
        self.links = [Link(i, t, anchor_slot=2 * i) for i, t in enumerate(trackers)]
        self.filter = AnchoredFilter(2 * len(trackers) + params.key_clones, params.accel_sd_m_s2,
                                     params.velocity_clones)
        self._free = list(range(2 * len(trackers), 2 * len(trackers) + params.key_clones))
        self._outputs = OutputClones()  # the velocity's covariance
        self._started = False
        self._lost = False
        self._last_update_s: float | None = None
        self._R_W_C: np.ndarray | None = None
        self.reset_counter = 0
        self.noise_scale = 1.0  # both trackers' covariances times this (_adapt)
        self._nis_mean = 3.0
        self._outliers = OutlierCheck(params.outlier_chi2, params.outlier_prior_dof, params.noise_adapt_gain)
        self.frames = 0
        self.coasted = 0
        self.last_part_ms: dict[str, float] = {}

    # ------------------------------------------------------------------ API
    def track(self, frame: RgbdFrame, attitude: AttitudeSource) -> TrackResult:
        # The measurement model takes NI-SLAM's attitude error per frame as
        # white (measurements.py): the attitude's fit is not widened here.
        attitude = without_widening(attitude)
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

    def backend_step(self) -> bool:
        """One unit of a part's back-end work (FastORB's local mapping), for
        the loop's idle time; False when no part has any."""
        for link in self.links:
            step = getattr(link.tracker, "backend_step", None)
            if step is not None and step():
                return True
        return False

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
        return {"frames": self.frames, "frames_coasted": self.coasted,
                "noise_scale": round(self.noise_scale, 3),
                "outlier_scale": round(self._outliers.scale, 3), "trackers": per}

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

        measured: list[tuple] = []
        to_anchor: list[tuple[Link, TrackResult, str]] = []
        for link, r, ok in zip(self.links, results, trusted):
            if not ok:
                reason = f"lost: {r.lost_reason or 'untrusted'}"
                link.left_out[reason] += 1
                left_out.append((link.name, reason))
                continue
            m, ref, keyed = measured_by(r)
            if not link.anchored:
                to_anchor.append((link, r, "joined"))
                continue
            why = self._reference(link, r, m, ref, keyed)
            if why is not None:
                link.left_out[why] += 1
                left_out.append((link.name, why))
                to_anchor.append((link, r, why))
                continue
            R = self._cov(link, r)
            if not np.all(np.isfinite(R)):
                link.left_out["no covariance"] += 1
                left_out.append((link.name, "no covariance"))
                to_anchor.append((link, r, "no covariance"))
                continue
            z = link.R_map @ (m - link.o)
            measured.append((link, r, z, R, self.filter.nis(link.anchor_slot, z, R), m))

        for link, r, *_ in measured:
            self._follow_axes(link, r, R_att)
        accepted, gated = self._gate(measured)
        used: list[tuple] = []
        outliers: list[tuple] = []
        for mm in sorted(accepted, key=lambda mm: mm[4]):  # the one the prediction agrees with most first
            link, r, z, R, nis, m = mm
            if used:
                # Against the state the first tracker updated: the prediction
                # alone is loose (the motion model allows cm per frame), so a
                # tracker going wild before it reports lost passes the gate
                # above (`circle`: FastORB 2-4 cm off for three frames moved
                # the output by 35 mm); against the other tracker it does
                # not (`outlier_chi2`, widened while the scale of S is still
                # being learnt: onboard.fusion.agreement). A loop closure is
                # exempt: it is meant to disagree with the other tracker's drift.
                after = self.filter.nis(link.anchor_slot, z, R)
                self._adapt(after)
                if not link.closing and self._outliers.check(after):
                    outliers.append((link, r, z, R, after, m))
                    continue
            self.filter.update(link.anchor_slot, z, R)
            used.append(mm)
            link.used += 1
            link.nis_sum += nis
            link.nis_n += 1
        accepted = sorted(used, key=lambda mm: mm[0].index)  # reported in the trackers' order
        for link, r, z, R, nis, m in gated:
            # Its motion disagrees with the other tracker and the motion
            # model: left out, and it goes on from here.
            link.left_out[GATED] += 1
            left_out.append((link.name, f"{GATED}, chi2 {nis:.0f}"))
            log.debug("t=%.3f: %s left out (gate), chi2 %.1f", t_s, link.name, nis)
            to_anchor.append((link, r, "disagreed"))
        for link, r, z, R, nis, m in outliers:
            # Off against the other tracker: one frame is an outlier, left
            # out alone (its reference kept: re-tying it would cost the clone
            # of its key, a loop closure's worth on tum_fr1_rpy); a second
            # in a row means its world moved, and it is tied back in.
            link.left_out[GATED] += 1
            left_out.append((link.name, f"{GATED}, chi2 {nis:.0f}"))
            if link.skipped:
                to_anchor.append((link, r, "disagreed"))
            link.skipped = True
        for link, r, z, R, nis, m in accepted:
            self._keep_last(link, r, m)
            link.skipped = False
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

    def _cov(self, link: Link, r: TrackResult) -> np.ndarray:
        """The tracker's measurement covariance this frame (W), agreement-scaled."""
        return COVARIANCE_MODELS.get(link.name, COVARIANCE_MODELS["fastorb"])(r, self.p) * self.noise_scale

    def _adapt(self, nis: float) -> None:
        """Scale both trackers' covariances so that they agree with each
        other as they claim (innovation-based adaptive estimation, Mehra
        1972): the second tracker's motion, once the first has updated the
        filter, is off by its own error and the first's, and its squared
        Mahalanobis distance averages 3 (3 dof) when the covariances are
        right. Their quality signals see the noise of a match, not what real
        data adds (a depth sensor's distortion, a shutter's timing), which on
        tum_fr1_rpy is several times larger. A slow step towards the scale
        that makes the mean 3; never below 1 (the signals' own figures)."""
        if not math.isfinite(nis):
            return
        g = self.p.noise_adapt_gain
        self._nis_mean += g * (min(nis, 10.0 * self.p.gate_chi2) - self._nis_mean)
        self.noise_scale = float(np.clip(self.noise_scale * (self._nis_mean / 3.0) ** g,
                                          1.0, self.p.noise_scale_max))

    def _reference(self, link: Link, r: TrackResult, m: np.ndarray, ref: tuple[int, int],
                   keyed: bool) -> str | None:
        """Point the tracker's anchor at the clone its measurement this frame
        is relative to; None, or why this frame can only tie it back in.

        A jump inside the tracker's own world is no motion. A tracker that
        measures against keys (NI-SLAM) tells its position relative to the
        key: on the same key that is motion since the key's clone; on a new
        key, made at its last frame, motion since that frame's fused position
        (the key inherits the fused error there, not the tracker's); on a key
        kept from before whose clone is kept too, a loop closure: its offset
        to that key ties the fused position to where that key was, with the
        covariance the filter carried since. A tracker that measures in its
        own world (FastORB) gives motion while its world stays (its reset
        counter unchanged); a restart or a re-localisation only ties it back in."""
        restarted = r.reset_counter != link.resets
        link.closing = False
        if keyed:
            key = ref[1]
            if key == link.ref[1]:
                link.ref = ref
                return None
            if key in link.keys:  # back on a key cloned before
                link.keys.move_to_end(key)
                link.anchor_slot, o, link.p_anchor = link.keys[key]
                link.o, link.ref, link.resets = o.copy(), ref, r.reset_counter
                link.closing = True
                return None
            if restarted or r.keyframe_reused or link.skipped:
                # (a key made at a frame left out: no clone of that frame)
                return "restarted" if restarted else "key re-used" if r.keyframe_reused else "key at a frame left out"
            slot = self._key_slot(link, key)
            self.filter.copy(link.last_slot, slot)
            if link.name == "nislam":
                self.filter.widen(slot, key_attitude_cov(r))
            link.anchor_slot, link.o, link.p_anchor, link.ref = slot, np.zeros(3), link.p_last.copy(), ref
            link.keys[key] = (slot, link.o, link.p_anchor)
            return None
        if restarted:
            return "restarted"
        if ref != link.ref:
            # Its newest key changed: its world is continuous there, so its
            # motion goes on from its last frame.
            self.filter.copy(link.last_slot, link.anchor_slot)
            link.o, link.p_anchor, link.ref = link.m_last.copy(), link.p_last.copy(), ref
        return None

    def _key_slot(self, link: Link, key: int) -> int:
        """A filter slot for `key`'s clone: its own, a free one, or the one of
        the key least recently used (the trackers keep few keys)."""
        if key in link.keys:
            return link.keys.pop(key)[0]
        if not self._free:
            old = next(iter(link.keys))
            self._free.append(link.keys.pop(old)[0])
            self.filter.forget(self._free[-1])
        return self._free.pop()

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
        s1, s2 = f._sl(m1[0].anchor_slot), f._sl(m2[0].anchor_slot)
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
        self.filter.start(t_s, p0, 0.0, self.p.initial_speed_sd_m_s)  # (drops the frozen outputs)
        self._started, self._lost = True, False
        self._last_update_s = t_s
        for link in self.links:
            link.anchored = False
            self._free += [slot for slot, *_ in link.keys.values()]
            link.keys.clear()

    def _follow_axes(self, link: Link, r: TrackResult, R_att: np.ndarray | None) -> None:
        """Refine the tracker's axes in W, R_i = mean of R_W_C(AHRS) R_i_C^T: one
        frame's pair is off by the attitude's noise and time offset (a degree
        turns a metre of motion by 1.7 cm), and FastORB's world slowly turns
        against the AHRS. A small step towards this frame's pair each frame
        (`axes_gain`): an exponential mean on SO(3)."""
        if R_att is None or self.p.axes_gain <= 0.0:
            return
        d = so3_log(link.R_map.T @ R_att @ np.asarray(r.R_W_C).T)
        link.R_map = link.R_map @ Rotation.from_rotvec(self.p.axes_gain * d).as_matrix()

    def _keep_last(self, link: Link, r: TrackResult, m: np.ndarray) -> None:
        """Clone the fused position of this frame as the tracker's last."""
        self.filter.anchor(link.last_slot)
        link.m_last, link.p_last = m.copy(), np.asarray(r.p_W_m, dtype=np.float64).copy()

    def _anchor(self, link: Link, r: TrackResult, R_att: np.ndarray | None, why: str) -> None:
        """Tie the tracker in at this frame: what it measures now is where the
        fused position is (after this frame's updates), so the output does not move."""
        m, ref, keyed = measured_by(r)
        if keyed:
            link.anchor_slot = self._key_slot(link, ref[1])
        self.filter.anchor(link.anchor_slot)
        # What the tracker measures from now on is relative to what it
        # measured here, error included: every later frame shares this one's
        # error, so the anchor carries it (without it the fused sd leaves out
        # each tie-in's error: 60 % coverage instead of 68 % with honest
        # trackers, tests/test_fusion_coverage.py).
        R = self._cov(link, r)
        if np.all(np.isfinite(R)):
            self.filter.widen(link.anchor_slot, R)
        self._keep_last(link, r, m)
        link.anchored, link.skipped = True, False
        link.ref, link.resets, link.o = ref, r.reset_counter, m.copy()
        link.p_anchor = link.p_last.copy()
        if keyed:
            link.keys[ref[1]] = (link.anchor_slot, link.o, link.p_anchor)
        if R_att is not None:  # without the AHRS the last mapping stays
            link.R_map = R_att @ np.asarray(r.R_W_C).T
        link.reanchors[why] += 1
        if why != "joined" or self.frames > 0:
            log.debug("%s tied back into the fused world (%s)", link.name, why)

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
        displacement = self._outputs.covariances(self.filter)
        self._outputs.record(self.filter, t_s)
        return TrackResult(
            t_s=t_s, state=TrackState.TRACKING, trusted=True, p_W_m=self.filter.p,
            R_W_C=R_W_C, pose_var=pose_var, quality=quality, psr=head.psr,
            keyframe_id=head.keyframe_id, new_keyframe=head.new_keyframe,
            reset_counter=self.reset_counter, lost_reason=None, shift_cells=head.shift_cells,
            tz_m=head.tz_m, res_m=head.res_m, rotation_residual_rad=head.rotation_residual_rad,
            attitude_offset_s=head.attitude_offset_s, matched_cells=head.matched_cells,
            finished_keyframes=clouds, keyframe_reused=head.keyframe_reused,
            keyframe_withdrawn=head.keyframe_withdrawn, keyframe_from_previous=head.keyframe_from_previous,
            contributors=contributors, left_out=left_out, displacement_cov=displacement,
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
        a = self.filter.x[self.filter._sl(link.anchor_slot)]
        p, R = link.to_world(cloud.p_W_m, cloud.R_W_C, a)
        return dataclasses.replace(cloud, p_W_m=p, R_W_C=R)
