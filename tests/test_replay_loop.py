"""A looped replay (`nislam run --loop`, the soak) restamps every frame with its
played time: the depth image's own stamp must move through the same map as
the colour's and the attitude's, mirrored on backward passes
(sim_replay/sources.py pass_direction, played_frame)."""

from __future__ import annotations

import numpy as np
import pytest

from onboard.core.messages import RgbdFrame
from sim_replay.sources import pass_direction, pingpong_schedule, played_frame

T = np.array([10.0, 10.033, 10.066, 10.1])
DEPTH_LAG_S = 0.005  # the depth image taken 5 ms after the colour


def test_depth_stamp_follows_the_played_clock_on_every_pass() -> None:
    passes = 4
    index, played = pingpong_schedule(T, passes, (T[0], T[-1]), 0.0)
    blank = np.zeros((2, 2, 3), np.uint8)
    for k, (i, t_play) in enumerate(zip(index, played)):
        frame = RgbdFrame(t_s=float(T[i]), bgr=blank, depth_m=np.ones((2, 2), np.float32),
                          depth_t_s=float(T[i] + DEPTH_LAG_S))
        out = played_frame(frame, float(t_play), pass_direction(index, k))
        forwards = (k // len(T)) % 2 == 0
        assert pass_direction(index, k) == (1 if forwards else -1)
        assert out.t_s == t_play
        expected = t_play + DEPTH_LAG_S if forwards else t_play - DEPTH_LAG_S
        assert out.depth_t_s == pytest.approx(expected, abs=1e-9)
        # ... which is where pingpong_schedule plays the attitude of that instant.
        period = T[-1] - T[0]
        p = k // len(T)
        att_t = (T[0] + p * period + (T[i] + DEPTH_LAG_S - T[0]) if forwards
                 else T[0] + p * period + (T[-1] - T[i] - DEPTH_LAG_S))
        assert out.depth_t_s == pytest.approx(att_t, abs=1e-9)


def test_frames_without_their_own_depth_stamp_keep_none() -> None:
    frame = RgbdFrame(t_s=1.0, bgr=np.zeros((2, 2, 3), np.uint8), depth_m=np.ones((2, 2)))
    assert played_frame(frame, 5.0, -1).depth_t_s is None
