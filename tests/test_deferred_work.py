"""Work the pose does not need is done after the pose went out
(onboard/nislam/deferred.py): NI-SLAM's new key (Eq. 17) and key refinement
(Eq. 19) run in `finish_frame()`, which the service calls once the pose is
handed to the outputs and their threads are woken. Checked by the order of
events, not by timing, and against the same work done in place: the poses,
key ids and key clouds are identical."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from fake_results import FakeCamera, NullRunner, ScriptedTracker
from test_nislam import INTR, Scene, _errors_mm, _pan_out_and_back, _params, _track_poses

from onboard.app import service as service_mod
from onboard.app.config import load_config
from onboard.app.service import Service
from onboard.app.sources import Sources
from onboard.core.attitude import AttitudeBuffer
from onboard.core.messages import RgbdFrame, TrackResult
from onboard.nislam import correlation, deferred
from onboard.nislam.tracker import NislamTracker
from onboard.outputs.wake import Wake


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene(seed=21)


# ------------------------------------------------------------------ the tracker
def _pan(scene: Scene, in_place: bool, finish: bool, monkeypatch: pytest.MonkeyPatch):
    """The pan out and back of test_nislam (new keys, refinement, a key
    re-used) with psr_keyframe 150 (> psr_refine: a frame can refine its key
    and then replace it); the deferred work done in place (as before it was
    deferred), after each frame (`finish`), or at the next frame's start."""
    with monkeypatch.context() as m:
        if in_place:
            m.setattr(deferred.Deferred, "add", lambda self, target, job: job())
        tracker = NislamTracker(INTR, _params(psr_keyframe=150.0, map_keyframes=16))
        if finish:
            track = tracker.track

            def track_and_finish(frame, att):
                r = track(frame, att)
                tracker.finish_frame()
                return r
            tracker.track = track_and_finish  # type: ignore[method-assign]
        results = _track_poses(tracker, scene, _pan_out_and_back())
        return results, tracker.finish()


def test_deferred_work_leaves_poses_keys_and_clouds_as_done_in_place(scene, monkeypatch):
    ref, ref_last = _pan(scene, in_place=True, finish=False, monkeypatch=monkeypatch)
    assert sum(r.new_keyframe for r in ref) == 2 and ref[-1].keyframe_reused
    for finish in (True, False):
        got, last = _pan(scene, in_place=False, finish=finish, monkeypatch=monkeypatch)
        for a, b in zip(ref, got, strict=True):
            assert np.array_equal(a.p_W_m, b.p_W_m)
            assert np.array_equal([a.psr], [b.psr], equal_nan=True)  # the first: NaN
            assert (a.keyframe_id, a.new_keyframe, a.keyframe_reused) == \
                (b.keyframe_id, b.new_keyframe, b.keyframe_reused)
            assert [c.keyframe_id for c in a.finished_keyframes] == \
                [c.keyframe_id for c in b.finished_keyframes]
            for ca, cb in zip(a.finished_keyframes, b.finished_keyframes, strict=True):
                assert np.array_equal(ca.depth_m, cb.depth_m)  # refined before handed out
                assert np.array_equal(ca.gray, cb.gray)
        assert np.array_equal(ref_last.depth_m, last.depth_m)
    assert max(np.max(np.abs(e)) for e in _errors_mm(ref, _pan_out_and_back())) < 2.0


def test_a_new_key_is_made_after_the_pose_not_before(scene, monkeypatch):
    """The frame that starts a key (Eq. 17) returns its pose with the new
    key's id, but the key's filter is trained only in finish_frame()."""
    trained: list[int] = []
    train = correlation.KernelCorrelationFilter.train
    monkeypatch.setattr(correlation.KernelCorrelationFilter, "train",
                        lambda self, x: (trained.append(1), train(self, x))[1])
    tracker = NislamTracker(INTR, _params(psr_keyframe=150.0))
    poses = _pan_out_and_back()
    first = _track_poses(tracker, scene, poses[:1])
    assert len(trained) == 1  # a first key: nothing to pose against before it
    tracker.finish_frame()
    for k in range(1, len(poses)):
        n = len(trained)
        r = _track_poses(tracker, scene, [poses[k]], t0=k / 30.0)[0]
        assert len(trained) == n, "a key was trained before the pose was returned"
        tracker.finish_frame()
        if r.new_keyframe:
            assert len(trained) == n + 1 and r.keyframe_id == tracker._key.keyframe_id
            break
    else:
        pytest.fail("no new key in the pan")
    assert first[0].new_keyframe


# ------------------------------------------------------------------ the service
class _Tracker(ScriptedTracker):
    """Steady trusted poses; records its calls."""

    def __init__(self, events: list[str]) -> None:
        super().__init__()
        self.events = events

    def track(self, frame: RgbdFrame, attitude) -> TrackResult:
        self.events.append("track")
        return super().track(frame, attitude)

    def finish_frame(self) -> None:
        self.events.append("deferred")


class _Output:
    """Records the pose handed over and the wake-up of its sender thread."""

    def __init__(self, events: list[str]) -> None:
        self.events = events
        self.wake = Wake()
        self.wake.set_now = lambda: events.append("wake")  # type: ignore[method-assign]

    def wakeups(self):
        return (self.wake,)

    def publish(self, result: TrackResult) -> None:
        self.events.append("publish")
        self.wake.set()  # deferred by the service until it flushes

    def publish_keyframe(self, cloud) -> None:
        pass

    def publish_health(self, report) -> None:
        pass

    def device_states(self):
        return []

    def stats(self):
        return {}

    def close(self) -> None:
        pass


def test_the_service_hands_the_pose_over_before_the_deferred_work(monkeypatch):
    events: list[str] = []
    monkeypatch.setattr(service_mod, "make_outputs", lambda *a, **k: _Output(events))
    cfg = load_config(None, {"service.stats_period_s": 3600.0})
    sources = Sources("fake", FakeCamera(6), AttitudeBuffer(np.eye(3), 16, 0.1), NullRunner())
    svc = Service(cfg, sources, threading.Event(), tracker_factory=lambda *_: _Tracker(events))
    svc.run()
    frames = "".join(e[0] for e in events)
    # per frame: track, the pose to the outputs, their thread woken, then the deferred work
    assert frames == "tpwd" * 6, events
    assert svc.timing.stages["deferred"].n == 6
