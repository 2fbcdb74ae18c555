"""Fault injection: each fault kind lands in the damaged copy exactly as
specified, the source is untouched, the reader reports every kind, and a
replay of every damaged variant finishes, counts what it skipped and never
reports a pose for a frame it could not track."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from onboard import NislamError
from onboard.app.config import load_config
from onboard.app.replay import replay
from onboard.core.trajectory import read_tum
from sim_replay.fault_plan import KINDS, FaultItem, parse_spec
from sim_replay.faults import inject_faults
from sim_replay.sim import sim_options, simulate
from sim_replay.tum import open_sequence
from sim_replay.tum_files import read_file_list

SPEC_ALL = ("drop:2,dup:2,swap:1,truncate:2,corrupt:1,zero-depth:2,att-gap:0.4,att-nan:2,"
            "att-spike:2,clock-jump:1.5")


def _digest(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            h.update(p.relative_to(folder).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> Path:
    """A 5 s circle at 320x240, 15 Hz, with a realistic depth sensor."""
    out = tmp_path_factory.mktemp("clean") / "circle"
    simulate("circle", out, sim_options(seconds=5.0, camera_hz=15.0, width=320, height=240,
                                        texel_m=0.006, seed=5), progress=False)
    return out


@pytest.fixture(scope="module")
def clean_counts(clean) -> dict[str, int]:
    return _counts(clean)


@pytest.fixture(scope="module")
def damaged(clean, tmp_path_factory) -> tuple[Path, dict, str]:
    before = _digest(clean)
    dst = tmp_path_factory.mktemp("damaged") / "all"
    manifest = inject_faults(clean, dst, SPEC_ALL, seed=11)
    return dst, manifest, before


def _counts(seq_dir: Path) -> dict[str, int]:
    seq = open_sequence(seq_dir)
    for _ in seq:  # decoding finds the unreadable files and empty depth images
        pass
    return seq.skipped.as_dict()


def _lines(path: Path) -> list[tuple[float, str]]:
    return [(t, f) for t, f in read_file_list(path)[0]]


def _fault(manifest: dict, kind: str) -> dict:
    return next(f for f in manifest["faults"] if f["kind"] == kind)


# --------------------------------------------------------------------------- spec


def test_spec_parses_kinds_values_and_places():
    items = parse_spec("drop:3, swap ,att-gap:0.5@2,clock-jump,zero-depth:1@4.5")
    assert items == (FaultItem("drop", 3.0), FaultItem("swap", 1.0),
                     FaultItem("att-gap", 0.5, 2.0), FaultItem("clock-jump", 2.0),
                     FaultItem("zero-depth", 1.0, 4.5))
    assert [i.text() for i in items] == ["drop:3", "swap:1", "att-gap:0.5@2", "clock-jump:2",
                                         "zero-depth:1@4.5"]
    assert {i.kind for i in parse_spec(SPEC_ALL)} == set(KINDS)


@pytest.mark.parametrize(("spec", "message"), [
    ("explode:1", "unknown kind 'explode'"),
    ("drop:x", "not KIND"),
    ("drop:0", "whole number"),
    ("dup:1.5", "whole number"),
    ("att-gap:0.1", "longer than 0.2"),
    ("clock-jump:0.5", "at least 1"),
    ("drop:1@-2", "at least 0"),
])
def test_bad_specs_are_one_line_errors(spec, message):
    with pytest.raises(NislamError, match=message) as err:
        parse_spec(spec)
    assert "\n" not in str(err.value)


# --------------------------------------------------------------------------- the copy


def test_every_fault_is_in_the_copy_exactly_as_specified(clean, damaged):
    dst, manifest, before = damaged
    assert _digest(clean) == before  # the source is only read
    src_rgb, dst_rgb = _lines(clean / "rgb.txt"), _lines(dst / "rgb.txt")
    dst_depth = _lines(dst / "depth.txt")
    src_att = np.loadtxt(clean / "attitude.txt")
    dst_att = np.genfromtxt(dst / "attitude.txt")
    jump = _fault(manifest, "clock-jump")
    (t_jump,), (dt_jump,) = jump["stamps"], jump["seconds"]
    assert dt_jump == 1.5

    def src_time(t: float) -> float:
        """A copy stamp on the source's clock."""
        return t - dt_jump if t > t_jump + dt_jump / 2 else t

    # Clock jump: every stamp after it, in every file, moved by exactly 1.5 s.
    gt_src, gt_dst = read_tum(clean / "groundtruth.txt"), read_tum(dst / "groundtruth.txt")
    shift = gt_dst.t_s - gt_src.t_s
    assert np.allclose(np.unique(np.round(shift, 6)), [0.0, 1.5])
    assert np.all((shift > 0) == (gt_src.t_s > t_jump))
    assert np.allclose(gt_dst.p_xyz_m, gt_src.p_xyz_m)
    att_shift = dst_att[~np.isnan(dst_att[:, 1]), 0]
    assert np.isclose(np.diff(att_shift).max(), 1.5 + 0.01, atol=1e-5)

    dst_rgb_src_t = [round(src_time(t), 6) for t, _ in dst_rgb]
    # Dropped frames: neither listed nor on disk.
    for t in _fault(manifest, "drop")["stamps"]:
        ts = round(src_time(t), 6)
        assert ts not in dst_rgb_src_t
        name = dict((round(a, 6), f) for a, f in src_rgb)[ts]
        assert not (dst / name).exists() and (clean / name).exists()
    # Duplicated frames: listed twice in a row in both lists, same file.
    for t in _fault(manifest, "dup")["stamps"]:
        for lst in (dst_rgb, dst_depth):
            k = [i for i, (a, _f) in enumerate(lst) if abs(a - t) < 1e-6]
            assert len(k) == 2 and k[1] == k[0] + 1 and lst[k[0]] == lst[k[1]]
    # Swapped frames: the pair listed later frame first, in both lists.
    for t in _fault(manifest, "swap")["stamps"]:
        for lst in (dst_rgb, dst_depth):
            k = next(i for i, (a, _f) in enumerate(lst) if abs(a - t) < 1e-6)
            assert lst[k - 1][0] > lst[k][0] and lst[k + 1][0] > lst[k - 1][0]
    # Truncated colour images: the first half of the original bytes.
    for name in _fault(manifest, "truncate")["files"]:
        data = (clean / name).read_bytes()
        assert (dst / name).read_bytes() == data[: len(data) // 2]
    # Corrupt depth images: same size, at most 64 bytes differ, no longer decodable.
    for name in _fault(manifest, "corrupt")["files"]:
        a, b = (clean / name).read_bytes(), (dst / name).read_bytes()
        assert len(a) == len(b)
        assert 0 < sum(x != y for x, y in zip(a, b)) <= 64
        assert cv2.imread(str(dst / name), cv2.IMREAD_UNCHANGED) is None
    # Zero depth: a valid image, every pixel zero.
    for name in _fault(manifest, "zero-depth")["files"]:
        img = cv2.imread(str(dst / name), cv2.IMREAD_UNCHANGED)
        assert img.shape == (240, 320) and img.dtype == np.uint16 and not img.any()
    # Attitude gap: no sample inside, samples right before and after.
    gap = _fault(manifest, "att-gap")
    (g0,), (g1,) = gap["stamps"], gap["until"]
    assert np.isclose(g1 - g0, 0.4)
    inside = (dst_att[:, 0] >= g0) & (dst_att[:, 0] < g1)
    assert not inside.any()
    assert (np.abs(dst_att[:, 0] - (g0 - 0.01)) < 0.0101).any()
    # NaN samples at exactly the listed stamps.
    nan_t = dst_att[np.isnan(dst_att[:, 1]), 0]
    assert np.allclose(np.sort(nan_t), np.sort(_fault(manifest, "att-nan")["stamps"]))
    # Spikes: 20-45 deg off the source sample, the neighbours untouched.
    for t in _fault(manifest, "att-spike")["stamps"]:
        k = int(np.argmin(np.abs(dst_att[:, 0] - t)))
        j = int(np.argmin(np.abs(src_att[:, 0] - src_time(t))))
        ang = np.degrees((Rotation.from_quat(src_att[j, 1:]).inv()
                          * Rotation.from_quat(dst_att[k, 1:])).magnitude())
        assert 20.0 <= ang <= 45.0
        assert np.allclose(dst_att[k + 1, 1:], src_att[j + 1, 1:])
    expected = manifest["expected"]
    assert expected == {"dropped_frames": 2, "duplicate_stamps": 4, "out_of_order_stamps": 2,
                        "truncated_files": 2, "unreadable_files": 3, "empty_depth_frames": 2,
                        "attitude_gaps": 1, "attitude_nan_samples": 2, "attitude_spikes": 2,
                        "clock_jumps": 1}


def test_the_reader_reports_every_fault_kind(clean, clean_counts, damaged):
    dst, manifest, _ = damaged
    src, bad = clean_counts, _counts(dst)
    assert all(v == 0 for v in src.values()), src
    assert {k: bad[k] - src[k] for k in bad if bad[k] != src[k]} == manifest["expected"]
    assert json.loads((dst / "faults.json").read_text()) == manifest


def test_recorded_sequence_copy(shared_data, tmp_path):
    """The same on a real TUM recording without attitude.txt: attitude faults
    go into an attitude.txt made from the ground truth, camera.toml is
    written from the folder name's TUM camera."""
    src = shared_data / "fixtures" / "tum_fr3_office_16frames"
    before = _digest(src)
    m = inject_faults(src, tmp_path / "copy", "drop:1,dup:1,truncate:1,att-nan:2,att-spike:1",
                      seed=2)
    assert _digest(src) == before
    assert (tmp_path / "copy" / "camera.toml").is_file()
    assert m["attitude_source"].startswith("groundtruth.txt")
    a, b = _counts(src), _counts(tmp_path / "copy")
    assert {k: b[k] - a[k] for k in b if b[k] != a[k]} == m["expected"]


def test_refuses_to_damage_in_place_or_without_room(clean, tmp_path):
    with pytest.raises(NislamError, match="another folder"):
        inject_faults(clean, clean, "drop:1")
    with pytest.raises(NislamError, match="room for only"):
        inject_faults(clean, tmp_path / "x", "drop:500")


# --------------------------------------------------------------------------- replay


@pytest.mark.parametrize("spec", [
    "drop:3", "dup:2", "swap:2", "truncate:2", "corrupt:2", "zero-depth:3", "att-gap:0.5",
    "att-nan:3", "att-spike:3", "clock-jump:2", SPEC_ALL,
])
def test_replay_of_a_damaged_flight(clean, clean_counts, tmp_path, monkeypatch, spec):
    dst = tmp_path / "seq"
    manifest = inject_faults(clean, dst, spec, seed=4)
    src_counts = clean_counts
    # The plot costs more than tracking these 75 frames and proves nothing
    # here; a coarser grid keeps the eleven replays quick.
    monkeypatch.setattr("onboard.app.replay.plot_trajectory", lambda *a, **k: False)
    cfg = load_config(None, {"nislam.grid_width": 240, "nislam.grid_height": 180})
    result = replay(dst, cfg, tmp_path / "out", progress=False)
    m = result.metrics
    # Finishes, and counts what it skipped or noticed: the faults, nothing else.
    skipped = {k: v - src_counts[k] for k, v in m["skipped"].items() if v != src_counts[k]}
    assert skipped == manifest["expected"]
    seq = open_sequence(dst)
    usable = [f.t_s for f in seq]  # what the reader yields
    assert m["frames"] == len(usable)
    traj = read_tum(tmp_path / "out" / "trajectory.tum")
    # A pose only for tracked frames: as many poses as tracked frames (less
    # those the evaluation finds no ground truth for), every one at a frame the
    # reader yielded, none at a damaged frame.
    assert m["frames_tracked"] == m["frames"] - m["frames_lost"]
    assert len(traj) == m["frames_tracked"] - m["frames_without_groundtruth"]
    assert np.isin(np.round(traj.t_s, 6), np.round(usable, 6)).all()
    bad_t = [t for f in manifest["faults"]
             if f["kind"] in ("drop", "truncate", "corrupt", "zero-depth") for t in f["stamps"]]
    assert len(bad_t) == sum(manifest["expected"].get(k, 0) for k in (
        "dropped_frames", "unreadable_files", "empty_depth_frames"))
    assert not np.isin(np.round(bad_t, 6), np.round(traj.t_s, 6)).any()
    if any(f["kind"] == "att-gap" for f in manifest["faults"]):
        gap = _fault(manifest, "att-gap")
        (g0,), (g1,) = gap["stamps"], gap["until"]
        # Frames well inside the gap have no attitude: lost, never posed.
        in_gap = [t for t in usable if g0 + 0.02 < t < g1 - 0.03]
        assert in_gap and not np.isin(np.round(in_gap, 6), np.round(traj.t_s, 6)).any()
        assert m["lost_reasons"].get("no attitude", 0) >= len(in_gap)
    # Most of the flight is still tracked, against exact ground truth.
    assert m["frames_tracked"] > 0.8 * m["frames"]
    assert m["ate_rmse_m"] is not None and math.isfinite(m["ate_rmse_m"])


# --------------------------------------------------------------------------- reader rules


def test_reader_rules_for_stamps_and_attitude_samples(tmp_path):
    from sim_replay.tum_files import drop_stale_entries, read_attitude_file, stream_gaps

    rows = [(1.0, "a"), (2.0, "b"), (2.0, "b"), (4.0, "d"), (3.0, "c"), (5.0, "e")]
    kept, dup, ooo = drop_stale_entries(rows)
    assert [f for _t, f in kept] == ["a", "b", "d", "e"] and (dup, ooo) == (1, 1)
    # 30 Hz with 2 ms jitter: 1 + 3 frames missing, one 2.5 s jump.
    rng = np.random.default_rng(0)
    t = np.arange(300) / 30.0 + rng.uniform(-0.002, 0.002, 300)
    t = np.delete(t, [50, 120, 121, 122])
    t[200:] += 2.5
    dropped, jumps = stream_gaps(t)
    assert dropped == 4 and len(jumps) == 1 and np.isclose(jumps[0][1] - jumps[0][0], 2.5 + 1 / 30,
                                                             atol=0.005)
    # Attitude: a NaN line, a 30 deg spike, a 0.5 s gap; a sample written as
    # -q (the same rotation) is no spike.
    ts = np.arange(0.0, 5.0, 0.01)
    q = Rotation.from_rotvec(np.stack([0.2 * ts, 0.1 * np.sin(ts), 0 * ts], 1)).as_quat()
    q[100] = -q[100]
    q[200] = (Rotation.from_quat(q[200]) * Rotation.from_rotvec([0.0, 0.52, 0.0])).as_quat()
    lines = [f"{a:.6f} {b[0]:.9f} {b[1]:.9f} {b[2]:.9f} {b[3]:.9f}" for a, b in zip(ts, q)
             if not 3.0 <= a < 3.5]
    lines[300] = f"{ts[300]:.6f} nan nan nan nan"
    (tmp_path / "attitude.txt").write_text("\n".join(lines) + "\nnot a line\n")
    traj, report = read_attitude_file(tmp_path / "attitude.txt")
    assert (report.malformed_lines, report.nan_samples, report.spikes) == (1, 1, 1)
    assert len(report.gaps) == 1 and abs(report.gaps[0][1] - report.gaps[0][0] - 0.51) < 0.011
    assert len(traj) == len(lines) - 2 and 2.0 not in np.round(traj.t_s, 6)
