"""SwitchingTracker (onboard/fusion/switching.py): the fallback while the attitude is
missing, one world for the outputs, reset_counter bumped at each switch."""

from __future__ import annotations

import dataclasses

import numpy as np
from fake_results import track_result
from scipy.spatial.transform import Rotation

from onboard.core.messages import RgbdFrame, TrackResult
from onboard.fusion.switching import NO_ATTITUDE, SwitchingTracker

DT = 1.0 / 30.0


def truth(t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """A camera moving along x at 1 m/s while yawing at 30 deg/s."""
    return (np.array([t_s, 0.5 * np.sin(t_s), 1.0]),
            Rotation.from_euler("z", 30.0 * t_s, degrees=True).as_matrix())


class Attitude:
    """No attitude within `gap`; otherwise the true rotation."""

    def __init__(self, gap: tuple[float, float]) -> None:
        self.gap = gap

    def rotation_at(self, t_s: float) -> np.ndarray | None:
        return None if self.gap[0] <= t_s < self.gap[1] else truth(t_s)[1]


class Primary:
    """NI-SLAM's behaviour: lost with NO_ATTITUDE without attitude; restarted
    (own reset_counter + 1) at its last trusted position afterwards."""

    name = "nislam"

    def __init__(self) -> None:
        self.resets = 0
        self.lost = False
        self.last_p: np.ndarray | None = None
        self.offset: np.ndarray | None = None  # restart: its world slides

    def track(self, frame: RgbdFrame, attitude: Attitude) -> TrackResult:
        if attitude.rotation_at(frame.t_s) is None:
            self.lost = True
            return track_result(frame.t_s, trusted=False, lost_reason=NO_ATTITUDE,
                                reset_counter=self.resets)
        p, R = truth(frame.t_s)
        if self.offset is None:
            self.offset = np.zeros(3)
        if self.lost:
            self.resets += 1
            self.offset = self.last_p - p  # restarts where it was last
            self.lost = False
        self.last_p = p + self.offset
        return track_result(frame.t_s, self.last_p, R, reset_counter=self.resets)

    def finish(self) -> None:
        return None


class Fallback:
    """FastORB's behaviour: its own world, fixed by its first frame."""

    name = "fastorb"

    def __init__(self) -> None:
        self.T: tuple[np.ndarray, np.ndarray] | None = None  # its world in the true one

    def track(self, frame: RgbdFrame, attitude: Attitude) -> TrackResult:
        p, R = truth(frame.t_s)
        if self.T is None:
            self.T = (R, p)  # first camera pose = its origin
        R0, p0 = self.T
        return track_result(frame.t_s, R0.T @ (p - p0), R0.T @ R)

    def finish(self) -> None:
        return None


def run(tracker: SwitchingTracker, attitude: Attitude, n: int) -> list[TrackResult]:
    img = np.zeros((4, 4, 3), np.uint8)
    return [tracker.track(RgbdFrame(i * DT, img, np.zeros((4, 4), np.float32)), attitude)
            for i in range(n)]


def test_fallback_keeps_one_world_and_each_switch_bumps_the_reset_counter() -> None:
    gap = (1.0, 2.0)
    made: list[Fallback] = []

    def make() -> Fallback:
        made.append(Fallback())
        return made[-1]

    tracker = SwitchingTracker(Primary(), make, return_after_s=0.5)
    results = run(tracker, Attitude(gap), 120)
    assert all(r.trusted for r in results)
    names = []
    for i, r in enumerate(results):
        t = i * DT
        names.append("fastorb" if gap[0] <= t < gap[1] + 0.5 else "nislam")
    switch_in, switch_back = names.index("fastorb"), names.index("nislam", names.index("fastorb"))
    counters = [r.reset_counter for r in results]
    assert counters[:switch_in] == [0] * switch_in
    assert set(counters[switch_in:switch_back]) == {1}
    assert set(counters[switch_back:]) == {2}
    assert tracker.switches == 2 and len(made) == 1
    # The world is continuous: each tie costs one frame's motion and nothing more.
    errors = [np.linalg.norm(r.p_W_m - truth(i * DT)[0]) for i, r in enumerate(results)]
    step = np.linalg.norm(truth(DT)[0] - truth(0.0)[0])
    assert max(errors[:switch_in]) < 1e-12
    assert max(errors[switch_in:]) < 2.5 * step
    # The fallback's rotation is tied into the AHRS world; the primary's stays the AHRS's.
    for i in (switch_in + 5, switch_back + 5):
        R_err = results[i].R_W_C.T @ truth(i * DT)[1]
        assert np.degrees(np.linalg.norm(Rotation.from_matrix(R_err).as_rotvec())) < 1.1


def test_without_a_fallback_the_primary_reports_lost_and_restarts() -> None:
    tracker = SwitchingTracker(Primary(), None)
    results = run(tracker, Attitude((1.0, 1.5)), 60)
    lost = [r for r in results if not r.trusted]
    assert lost and all(r.lost_reason == NO_ATTITUDE for r in lost)
    assert results[-1].reset_counter == 1 and tracker.switches == 0


class LoopingFallback(Fallback):
    """A fallback that has closed 5 loops before it is switched to (a count a
    switch must not read as new), and closes one more at `loop_at_s`, moving a
    key frame that sits at the true pose of time 1.2 s."""

    def __init__(self, loop_at_s: float) -> None:
        super().__init__()
        self.loop_at_s = loop_at_s

    def track(self, frame: RgbdFrame, attitude: Attitude) -> TrackResult:
        result = super().track(frame, attitude)
        closed = frame.t_s >= self.loop_at_s
        moved = ()
        if closed and frame.t_s < self.loop_at_s + DT / 2:
            p, R = truth(1.2)
            R0, p0 = self.T
            moved = ((7, R0.T @ (p - p0), R0.T @ R),)
        return dataclasses.replace(result, loop_corrections=5 + int(closed), moved_keyframes=moved)


def test_loop_corrections_count_once_and_moved_keys_come_into_our_world() -> None:
    tracker = SwitchingTracker(Primary(), lambda: LoopingFallback(loop_at_s=1.5), return_after_s=0.5)
    results = run(tracker, Attitude((1.0, 2.0)), 120)
    counts = [r.loop_corrections for r in results]
    i_loop = int(round(1.5 / DT))
    # The switch in (at 1.0 s) and back (2.5 s) change nothing; the loop counts once.
    assert counts[:i_loop] == [0] * i_loop and set(counts[i_loop:]) == {1}
    [moved] = [r.moved_keyframes for r in results if r.moved_keyframes]
    (key_id, p_W, R_W), = moved
    assert key_id == 7
    step = np.linalg.norm(truth(DT)[0] - truth(0.0)[0])
    assert np.linalg.norm(p_W - truth(1.2)[0]) < 2.5 * step  # in the outputs' world, not FastORB's
    R_err = R_W.T @ truth(1.2)[1]
    assert np.degrees(np.linalg.norm(Rotation.from_matrix(R_err).as_rotvec())) < 1.1
