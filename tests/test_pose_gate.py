"""Nothing untrusted goes out: the list reader keeps the longest rising run of
stamps (one bad line costs that line only), and the pose gate never passes a
pose the motion model cannot explain as trusted."""

from __future__ import annotations

import numpy as np

from onboard.core.messages import TrackResult, TrackState
from onboard.core.pose_gate import GateSettings, PoseGate
from sim_replay.tum_files import drop_stale_entries


def _result(t: float, p, counter: int = 0, trusted: bool = True) -> TrackResult:
    return TrackResult(
        t_s=t, state=TrackState.TRACKING, trusted=trusted,
        p_W_m=None if p is None else np.asarray(p, float),
        R_W_C=None if p is None else np.eye(3), pose_var=np.full(6, 1e-4), quality=80,
        psr=20.0, keyframe_id=1, new_keyframe=False, reset_counter=counter, lost_reason=None,
        shift_cells=(0.0, 0.0), tz_m=0.0, res_m=0.01, rotation_residual_rad=np.zeros(3),
        attitude_offset_s=0.0, matched_cells=100)


def test_a_garbage_line_stamped_ahead_costs_only_that_line():
    t = 1000.0 + np.arange(40) / 30.0
    rows = [(float(x), f"rgb/{i}.png") for i, x in enumerate(t)]
    # A garbage line stamped 10 frames ahead, placed among good ones: the old
    # "later than everything kept" rule kept it and dropped the next 10 frames.
    rows.insert(20, (float(t[30]) + 0.001, "rgb/garbage.png"))
    kept, dup, ooo = drop_stale_entries(rows)
    assert [f for _t, f in kept] == [f"rgb/{i}.png" for i in range(40)]
    assert (dup, ooo) == (0, 1)
    # A swap still costs one frame; a repeated line is a duplicate.
    rows = [(1.0, "a"), (3.0, "c"), (2.0, "b"), (4.0, "d"), (4.0, "d2")]
    kept, dup, ooo = drop_stale_entries(rows)
    assert [f for _t, f in kept] == ["a", "c", "d"] and (dup, ooo) == (1, 1)


def test_a_jump_after_a_gap_is_never_sent_trusted_and_ends_in_a_reset():
    gate = PoseGate()
    out = []
    t, x = 10.0, 0.0
    for _ in range(30):  # 0.1 m/s along x at 30 Hz
        out.append(gate.check(_result(t, (x, 0, 1))))
        t, x = t + 1 / 30, x + 0.1 / 30
    assert all(r.trusted for r in out) and gate.stats.rejected == 0
    # The case of the issue: 0.33 s without frames, then the tracker 0.49 m
    # off while the vehicle moved 0.03 m; it goes on from the wrong place.
    t += 0.33
    x += 0.033
    after = [gate.check(_result(t + k / 30, (x + 0.49 + 0.1 * k / 30, 0, 1))) for k in range(8)]
    assert not after[0].trusted and after[0].p_W_m is None and gate.stats.checks == 1
    assert "step 0.4" in after[0].lost_reason
    settle = GateSettings().settle_frames
    assert not any(r.trusted for r in after[:settle])
    # Trusted again only as a new segment: reset_counter one higher.
    assert all(r.trusted and r.reset_counter == 1 for r in after[settle:])
    assert gate.stats.jumps == 1 and gate.stats.resets == 1
    assert gate.stats.rejected == settle


def test_real_manoeuvres_and_tracker_resets_pass_the_gate():
    rng = np.random.default_rng(0)
    gate = PoseGate()
    t = np.arange(0, 10, 1 / 30)
    # 3.7 m/s^2 peak acceleration (a fast indoor figure eight), 1 cm pose noise,
    # and one 0.13 s frame gap (fr1/rpy has one).
    p = np.stack([1.5 * np.sin(1.4 * t), 0.3 * np.sin(2.8 * t), 0.1 * np.sin(t)], 1)
    p += rng.normal(0, 0.01, p.shape)
    keep = np.ones(len(t), bool)
    keep[100:104] = False
    res = [gate.check(_result(a, b)) for a, b in zip(t[keep], p[keep])]
    assert all(r.trusted for r in res) and gate.stats.rejected == 0
    # The tracker's own reset (its counter moves) is a new world: no jump.
    r = gate.check(_result(t[-1] + 1 / 30, (5.0, 5.0, 5.0), counter=1))
    assert r.trusted and r.reset_counter == 1
    # After a gap longer than one pose can be judged over: the next poses are
    # checked (withheld), then trusted as they are when the step is possible ...
    t1 = t[-1] + 3.0
    res = [gate.check(_result(t1 + k / 30, (5.5, 5.0, 5.0), counter=1)) for k in range(4)]
    assert [r.trusted for r in res] == [False, False, True, True]
    assert res[-1].reset_counter == 1 and gate.stats.resets == 0 and gate.stats.checks == 1
    # ... and with a reset when it is not (50 m in 3 s).
    t2 = t1 + 3.0
    res = [gate.check(_result(t2 + k / 30, (55.5, 5.0, 5.0), counter=1)) for k in range(4)]
    assert [r.trusted for r in res] == [False, False, True, True]
    assert res[-1].reset_counter == 2 and gate.stats.resets == 1 and gate.stats.jumps == 1
    # Untrusted results pass through untouched.
    r = gate.check(_result(t2 + 0.5, None, counter=1, trusted=False))
    assert not r.trusted and r.reset_counter == 2 and not gate.withheld
