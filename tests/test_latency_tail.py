"""Work taken off the pose path for the latency tail (docs/latency.md, "Work
the pose does not wait for"), checked by counts and against the work done
as before, never by timing: the results stay identical.

- NI-SLAM measures the residual rotation (the time-offset calibration's
  input) only on frames whose rate difference g lets the estimate use it; on
  a steady turn it is never measured, and the poses and the estimate are those
  of measuring it on every frame.
- The residual fit itself runs after the pose: the pose does not use it.
- A key made inside track() (the first, a restart, after a failed match) is
  matched at once, but its colour (for the map only) is gathered after the
  pose: the clouds handed out are those of gathering it in place.
- A turn that carries the view off the key's grid hands the key over on
  the last firm frame, after its pose (kept keys tried, or a new key), not
  on the failed match that follows.
- The service, bench and replay keep freed memory for the next frame
  (onboard/app/allocator.py): no page faults for arrays made every frame.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from test_nislam import (
    DT,
    INTR,
    Scene,
    _errors_mm,
    _pan_out_and_back,
    _params,
    _rot,
    _track_poses,
)

from onboard.core.messages import RgbdFrame
from onboard.nislam import calibration, deferred
from onboard.nislam import tracker as tracker_mod
from onboard.nislam.tracker import NislamTracker


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene(seed=21)


class PanAttitude:
    """Exact attitude at any time of a pan about the camera's y axis by
    `angle_deg(t)` (the calibration reads rates 20 ms either side)."""

    def __init__(self, angle_deg):
        self.angle_deg = angle_deg

    def rotation_at(self, t_s: float) -> np.ndarray:
        return _rot(y=self.angle_deg(t_s))


def _pan(scene: Scene, angle_deg, measure_always: bool, monkeypatch) -> tuple[list, object, int]:
    """Track 13 frames of the pan with the time-offset calibration on;
    (results, the calibration's state, residual fits made). With
    `measure_always` the residual is fitted on every match, as before."""
    fits = []
    fit = calibration.RotationResidual.residual
    monkeypatch.setattr(calibration.RotationResidual, "residual",
                        lambda self, *a: (fits.append(1), fit(self, *a))[1])
    tracker = NislamTracker(INTR, _params(calibrate_time_offset=True, psr_keyframe=20.0))
    if measure_always:
        tracker._calib.informative = lambda g: True  # the tracker's check only: update() keeps its own
    att = PanAttitude(angle_deg)
    results = []
    for k in range(13):
        t = round(k * DT, 9)
        bgr, depth = scene.render(att.rotation_at(t), np.array([0.002 * k, 0.0, 0.0]))
        results.append(tracker.track(RgbdFrame(t, bgr, depth), att))
        tracker.finish_frame()
    c = tracker._calib
    return results, (c.n, c.num, c.den, c.offset_s), len(fits)


@pytest.mark.parametrize("turn", ["steady", "speeding_up"])
def test_the_residual_is_fitted_only_when_the_calibration_can_use_it(scene, monkeypatch, turn):
    """A steady 45 deg/s turn: the key's and the frame's rates are alike
    (g = 0), no fit is made, where measuring always made one per frame. A
    turn speeding up from rest (300 deg/s^2): fits where g is large enough
    only. Both: poses, key ids, PSR and the calibration's state identical."""
    angle = (lambda t: 45.0 * t) if turn == "steady" else (lambda t: 150.0 * t * t)
    ref, ref_calib, ref_fits = _pan(scene, angle, True, monkeypatch)
    got, calib, fits = _pan(scene, angle, False, monkeypatch)
    assert all(r.trusted for r in ref)
    matched = sum(1 for r in ref[1:])  # every frame after the first is matched once
    assert ref_fits >= matched
    if turn == "steady":
        assert fits == 0 and ref_calib[0] == 0
    else:
        assert 0 < fits < ref_fits and calib[0] > 0  # some frames informative, not all
    assert calib == ref_calib
    for a, b in zip(ref, got, strict=True):
        assert np.array_equal(a.p_W_m, b.p_W_m)
        assert np.array_equal([a.psr], [b.psr], equal_nan=True)
        assert (a.keyframe_id, a.new_keyframe) == (b.keyframe_id, b.new_keyframe)
        assert a.attitude_offset_s == b.attitude_offset_s


def _residual_fits(scene: Scene, in_place: bool, monkeypatch) -> tuple[list, tuple, list[bool]]:
    """The pan speeding up, tracked with finish_frame() after each frame;
    (results, the calibration's state, for each residual fit whether it ran
    inside track()). `in_place`: every queued job runs where it is queued."""
    inside = [False]
    where: list[bool] = []
    fit = calibration.RotationResidual.residual
    with monkeypatch.context() as m:
        m.setattr(calibration.RotationResidual, "residual",
                  lambda self, *a: (where.append(inside[0]), fit(self, *a))[1])
        if in_place:
            m.setattr(deferred.Deferred, "add", lambda self, target, job: job())
        tracker = NislamTracker(INTR, _params(calibrate_time_offset=True, psr_keyframe=20.0))
        att = PanAttitude(lambda t: 150.0 * t * t)
        results = []
        for k in range(13):
            t = round(k * DT, 9)
            bgr, depth = scene.render(att.rotation_at(t), np.array([0.002 * k, 0.0, 0.0]))
            inside[0] = True
            results.append(tracker.track(RgbdFrame(t, bgr, depth), att))
            inside[0] = False
            tracker.finish_frame()
        c = tracker._calib
        return results, (c.n, c.num, c.den, c.offset_s), where


def test_the_residual_fit_runs_after_the_pose(scene, monkeypatch):
    """The pose does not use the residual rotation (it moves the offset for
    the next frames' attitude lookups): fitted after the pose, the poses, the
    calibration and the residuals reported are those of fitting in place."""
    ref, ref_calib, ref_where = _residual_fits(scene, True, monkeypatch)
    got, calib, where = _residual_fits(scene, False, monkeypatch)
    assert ref_where and all(ref_where)  # in place: on the pose's path
    assert len(where) == len(ref_where) and not any(where)
    assert calib == ref_calib and calib[0] > 0
    assert [r.attitude_offset_s for r in got] == [r.attitude_offset_s for r in ref]
    for a, b in zip(ref, got, strict=True):
        assert np.array_equal(a.p_W_m, b.p_W_m) and a.keyframe_id == b.keyframe_id
        assert np.array_equal(a.rotation_residual_rad, b.rotation_residual_rad)
    assert any(np.any(r.rotation_residual_rad != 0) for r in got)


def _clouds(scene: Scene, in_place: bool, monkeypatch) -> tuple[list, list, list[bool]]:
    """The pan out and back (first key, new keys, a key re-used) tracked with
    finish_frame() after each frame; (results, every key cloud handed out,
    for each colour projection whether it ran inside track())."""
    inside = [False]
    coloured: list[bool] = []
    project = tracker_mod.project

    def spy(*a, with_colour=False, **kw):
        if with_colour:
            coloured.append(inside[0])
        return project(*a, with_colour=with_colour, **kw)

    with monkeypatch.context() as m:
        m.setattr(tracker_mod, "project", spy)
        if in_place:  # as before any work was deferred
            m.setattr(deferred.Deferred, "add", lambda self, target, job: job())
        tracker = NislamTracker(INTR, _params(psr_keyframe=150.0, map_keyframes=16))
        track = tracker.track

        def track_then_finish(frame, att):
            inside[0] = True
            r = track(frame, att)
            inside[0] = False
            tracker.finish_frame()
            return r
        tracker.track = track_then_finish  # type: ignore[method-assign]
        poses = _pan_out_and_back()
        poses.append(poses[-1])  # the first frame on the re-used key
        results = _track_poses(tracker, scene, poses)
        clouds = [c for r in results for c in r.finished_keyframes] + [tracker.finish()]
    return results, clouds, coloured


def test_a_key_made_in_track_gets_its_colour_after_the_pose(scene, monkeypatch):
    ref, ref_clouds, ref_coloured = _clouds(scene, True, monkeypatch)
    got, clouds, coloured = _clouds(scene, False, monkeypatch)
    assert ref_coloured[0] is True  # the first key's colour was on its pose's path
    assert coloured and not any(coloured)  # now never inside track()
    assert len(coloured) == len(ref_coloured) == sum(r.keyframes_added for r in ref)
    for a, b in zip(ref, got, strict=True):
        assert np.array_equal(a.p_W_m, b.p_W_m) and a.keyframe_id == b.keyframe_id
    assert [c.keyframe_id for c in clouds] == [c.keyframe_id for c in ref_clouds]
    for a, b in zip(ref_clouds, clouds, strict=True):
        assert a.bgr.any() and np.array_equal(a.bgr, b.bgr)
        assert np.array_equal(a.gray, b.gray) and np.array_equal(a.depth_m, b.depth_m)


FRAMES = """
import resource, sys
import numpy as np
from onboard.app.allocator import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
def frame():  # a frame's grids, made and freed (5.5 MB)
    grids = [np.ones((360, 480), np.float32) for _ in range(8)]
    del grids
for _ in range(3):
    frame()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    frame()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def test_freed_memory_is_kept_for_the_next_frame():
    """In a process of its own (the setting is process-wide): with glibc's
    own thresholds every frame faults its grids in again (~170 pages each);
    with keep_freed_memory() none after the first frames."""
    def faults(mode: str) -> int:
        out = subprocess.run([sys.executable, "-c", FRAMES, mode], capture_output=True,
                             text=True, timeout=60, check=True)
        return int(out.stdout.strip())
    assert faults("glibc") > 20 * 8 * 100
    assert faults("keep") < 100


def test_a_firm_frame_leaving_the_grid_tries_kept_keys_after_its_pose(scene, monkeypatch):
    """The slow pan out to 30 deg (key 1 made at 25 deg, below) and back: near
    0 deg the frames leave key 1's grid while still matched firmly (PSR ~80)
    and key 0 is in view again. The frame is posed on key 1 and announces
    key 2; key 0 is matched in finish_frame() and re-used, so the next frame
    is measured against it and says so (re-used, key 2 withdrawn)."""
    inside = [False]
    matches: list[tuple[bool, int]] = []  # (inside track(), key id)
    match = NislamTracker._match

    def spy(self, key, *a, **kw):
        matches.append((inside[0], key.keyframe_id))
        return match(self, key, *a, **kw)

    monkeypatch.setattr(NislamTracker, "_match", spy)
    tracker = NislamTracker(INTR, _params(psr_keyframe=5.0, min_valid_fraction=0.5,
                                          map_keyframes=16))
    track = tracker.track
    per_frame: list[list[tuple[bool, int]]] = []

    def track_then_finish(frame, att):
        matches.clear()
        inside[0] = True
        r = track(frame, att)
        inside[0] = False
        tracker.finish_frame()
        per_frame.append(list(matches))
        return r
    tracker.track = track_then_finish  # type: ignore[method-assign]
    out = [(_rot(y=1.0 * k), np.array([0.01 * k, 0.0, 0.0])) for k in range(31)]
    poses = out + out[-2::-1] + out[:1]
    results = _track_poses(tracker, scene, poses)
    left = next(i for i, r in enumerate(results) if r.new_keyframe and r.reference_keyframe_id == 1)
    assert results[left].psr > 50.0 and results[left].keyframe_id == 2
    assert per_frame[left] == [(True, 1), (False, 0)]  # key 0 tried after the pose
    nxt = results[left + 1]
    assert nxt.reference_keyframe_id == 0 and nxt.keyframe_reused and nxt.keyframe_withdrawn
    assert sum(r.keyframes_added for r in results) == 2  # keys 0 and 1; 2 never made
    assert max(np.max(np.abs(e)) for e in _errors_mm(results, poses)) < 5.0


def test_a_view_leaving_the_key_grid_hands_over_before_the_match_fails(scene, monkeypatch):
    """A slow pan (1 deg and 10 mm a frame) with the match firm throughout
    (PSR > 70) and `min_valid_fraction` at 0.5: the frames cover 0.68 of the
    key's grid at first and 0.007 less each frame. The key is handed over
    (a new key, announced) on the frame after which the next would cover
    less than half, so no match against the current key fails. Before, the
    frame below half failed its match, and the pose waited for a key made
    from the frame before and a second match (measured: one failed match at
    frame 26, no key announced)."""
    failed: list[int] = []
    match = NislamTracker._match

    def spy(self, key, *a, **kw):
        out = match(self, key, *a, **kw)
        if out is None:
            failed.append(key.keyframe_id)
        return out

    monkeypatch.setattr(NislamTracker, "_match", spy)
    poses = [(_rot(y=1.0 * k), np.array([0.01 * k, 0.0, 0.0])) for k in range(36)]
    tracker = NislamTracker(INTR, _params(psr_keyframe=5.0, min_valid_fraction=0.5))
    results = _track_poses(tracker, scene, poses)
    assert failed == []
    handed = [i for i, r in enumerate(results) if r.new_keyframe and i > 0]
    assert len(handed) == 1 and results[handed[0]].psr > 50.0
    assert results[handed[0] + 1].reference_keyframe_id == results[handed[0]].keyframe_id
    assert max(np.max(np.abs(e)) for e in _errors_mm(results, poses)) < 5.0
