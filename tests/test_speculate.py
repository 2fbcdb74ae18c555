"""A kept key's match started early on a spare core (onboard/nislam/speculate.py)
cuts the slowest frames (a weakened match, then the kept keys) to about one
match without changing a pose: the tracker with a spare worker gives the poses
of the matches done in series, bit for bit, and does take the early match."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from test_nislam import INTR, Scene, _pan_out_and_back, _params, _track_poses

from onboard.nislam import speculate
from onboard.nislam.tracker import NislamTracker


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene(seed=21)


def _pan(scene: Scene, spare: ThreadPoolExecutor | None):
    """test_nislam's pan out and back: key 1 weakens on the way back and key
    0 is re-used before the pose (psr_keyframe 150)."""
    tracker = NislamTracker(INTR, _params(psr_keyframe=150.0, map_keyframes=16), spare)
    return _track_poses(tracker, scene, _pan_out_and_back())


def test_early_matches_give_the_poses_of_matches_in_series(scene, monkeypatch):
    ref = _pan(scene, None)
    assert ref[-1].keyframe_reused
    taken: list[bool] = []
    take = speculate.Speculation.take

    def counted(self, key, win):
        got = take(self, key, win)
        taken.append(got is not None)
        return got
    monkeypatch.setattr(speculate.Speculation, "take", counted)
    with ThreadPoolExecutor(1) as spare:
        got = _pan(scene, spare)
    assert any(taken)  # the re-use took the match started early
    for a, b in zip(ref, got, strict=True):
        assert np.array_equal(a.p_W_m, b.p_W_m)
        assert np.array_equal([a.psr], [b.psr], equal_nan=True)
        assert (a.keyframe_id, a.keyframe_reused, a.reset_counter) == \
            (b.keyframe_id, b.keyframe_reused, b.reset_counter)


def test_a_match_started_with_another_window_is_not_taken(scene):
    """The re-use guesses its candidates from the weakened match and looks
    the key's attitude up at the offset after this frame's calibration: a
    match started with another rotation or window is stale."""
    tracker = NislamTracker(INTR, _params(map_keyframes=16))
    _track_poses(tracker, scene, _pan_out_and_back(n=2))
    key = tracker._key
    assert key is not None
    cloud = tracker._prev.cloud
    win = speculate.search_window(key, key.t_s + 0.1, np.eye(3), tracker.p, fresh=True)
    with ThreadPoolExecutor(1) as spare:
        spec = speculate.Speculation(spare)

        class Still:
            def rotation_at(self, t_s):
                return key.R_W_C

        spec.start([key], cloud, key.t_s + 0.1, key.R_W_C, Still(), 0.0, tracker.shape,
                   (0.0, 0.0), tracker.p)
        turned = speculate.Window(win.r_rel @ np.diag([1.0, -1.0, -1.0]), win.centre_cells,
                                  win.radius_cells)
        assert spec.take(key, turned) is None
        wider = speculate.Window(win.r_rel, win.centre_cells, win.radius_cells + 1)
        assert spec.take(key, wider) is None
        raw = spec.take(key, win)
        assert raw is not None and raw.ok
        direct = speculate.measure(key, cloud, win, tracker.shape, (0.0, 0.0), tracker.p)
        assert raw.peak == direct.peak and raw.depth.tz_m == direct.depth.tz_m
        spec.settle()
        assert spec.take(key, win) is None  # settled: nothing left to take
