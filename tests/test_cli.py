"""`nislam replay` / `nislam bench` end to end, as a user runs them (subprocess)."""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from onboard.app.config import Config, load_config, with_tracker_resolved
from onboard.app.replay import RESULT_FILES, replay
from onboard.core.trajectory import read_tum
from onboard.outputs.ply import read_ply

REPO = Path(__file__).resolve().parents[1]
FIXTURE = "fixtures/tum_fr3_office_16frames"
FIXTURE_FRAMES = 16

REPLAY_KEYS = {
    "frames", "frames_tracked", "frames_lost", "tracked_share", "keyframes", "resets",
    "ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "frame_ms_median", "frame_ms_p95",
    "frame_ms_max", "hz", "attitude_source", "attitude_offset_s", "skipped", "tracker",
    "sequence", "rpe_lag1_m", "rpe_lag3_m", "rpe_lag10_m", "rpe_lag30_m", "rpe_rot_lag1_deg",
    "path_length_ratio", "keyframe_changes", "keyframe_jump_median_m", "keyframe_jump_max_m",
}
BENCH_KEYS = {"frames", "frame_ms_median", "frame_ms_p95", "frame_ms_max", "hz", "tracker"}


def nislam(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    # PYTHONPATH: the checkout works even before `pip install -e .`.
    env = dict(os.environ, MPLBACKEND="Agg")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    return subprocess.run(
        [sys.executable, "-m", "onboard.app.cli", *args],
        cwd=cwd or REPO, env=env, capture_output=True, text=True, timeout=300,
    )


@pytest.fixture(scope="module")
def fixture_seq(shared_data: Path) -> Path:
    return shared_data / FIXTURE


@pytest.fixture(scope="module")
def replay_out(fixture_seq: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One replay of the 16-frame fixture, shared by the checks below."""
    out = tmp_path_factory.mktemp("replay")
    proc = nislam("replay", str(fixture_seq), "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    assert "ATE RMSE" in proc.stdout and "frames      16" in proc.stdout
    assert "RPE frames" in proc.stdout and "key changes" in proc.stdout
    return out


def test_replay_writes_every_result(replay_out: Path) -> None:
    for name in RESULT_FILES:
        assert (replay_out / name).is_file(), name
    metrics = json.loads((replay_out / "metrics.json").read_text())
    assert REPLAY_KEYS <= set(metrics)
    assert metrics["frames"] == FIXTURE_FRAMES
    assert metrics["frames_tracked"] + metrics["frames_lost"] == FIXTURE_FRAMES
    assert metrics["frames_tracked"] >= 10
    assert 0.0 < metrics["ate_rmse_m"] < 0.05
    assert metrics["rpe_lag1_m"] > 0.0 and metrics["path_length_ratio"] > 0.0
    assert metrics["rpe_lag30_m"] is None  # 16 frames: no pair 30 apart
    assert metrics["keyframes"] >= 1
    assert metrics["frame_ms_median"] > 0 and metrics["hz"] > 0
    assert metrics["tracker"] == "nislam"
    # The configuration it ran with, the tracker named ("auto" chose NI-SLAM).
    assert load_config(replay_out / "config.toml") == with_tracker_resolved(Config(), service=False)
    xyz, rgb = read_ply(replay_out / "map.ply")
    assert len(xyz) == metrics["map_points"] > 1000 and rgb.any()
    assert (replay_out / "trajectory.png").read_bytes().startswith(b"\x89PNG")


def test_trajectory_and_groundtruth_share_stamps(replay_out: Path) -> None:
    est = read_tum(replay_out / "trajectory.tum")
    gt = read_tum(replay_out / "groundtruth_at_frames.tum")
    assert len(est) == len(gt) == json.loads((replay_out / "metrics.json").read_text())[
        "frames_evaluated"
    ]
    np.testing.assert_array_equal(est.t_s, gt.t_s)


def test_ate_equals_evo_ape(replay_out: Path, evo) -> None:
    metrics = json.loads((replay_out / "metrics.json").read_text())
    stats, _errors = evo(
        "evo_ape",
        ["tum", str(replay_out / "groundtruth_at_frames.tum"),
         str(replay_out / "trajectory.tum"), "-a"],
    )
    assert metrics["ate_rmse_m"] > 0.0
    assert metrics["ate_rmse_m"] == pytest.approx(stats["rmse"], abs=1e-6)


def test_second_run_keeps_foreign_files(fixture_seq: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    for _ in range(2):
        proc = nislam("replay", str(fixture_seq), "--out", str(out), "--max-frames", "5",
                      "--quiet")
        assert proc.returncode == 0, proc.stderr
    assert (out / "notes.txt").read_text() == "mine"
    assert json.loads((out / "metrics.json").read_text())["frames"] == 5
    assert sorted(p.name for p in out.iterdir()) == sorted([*RESULT_FILES, "notes.txt"])


def test_replay_flags_reach_the_config(fixture_seq: Path, tmp_path: Path) -> None:
    proc = nislam(
        "replay", str(fixture_seq), "--out", str(tmp_path), "--max-frames", "4", "--quiet",
        "--attitude-noise-deg", "0.5", "--attitude-offset-ms", "10", "--seed", "7",
        "--attitude-bias-deg-per-sqrt-s", "0.1", "--no-attitude-calibration",
    )
    assert proc.returncode == 0, proc.stderr
    cfg = load_config(tmp_path / "config.toml")
    assert cfg.attitude.noise_deg == 0.5 and cfg.attitude.offset_ms == 10.0
    assert cfg.attitude.seed == 7 and cfg.attitude.bias_deg_per_sqrt_s == 0.1
    assert cfg.nislam.calibrate_time_offset is False
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert "noise 0.5 deg" in metrics["attitude_source"]


def test_default_out_dir_is_results_sequence_name(fixture_seq: Path, tmp_path: Path) -> None:
    proc = nislam("replay", str(fixture_seq), "--max-frames", "3", "--quiet", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "results" / fixture_seq.name / "metrics.json").is_file()


def test_bench_json_is_one_object(fixture_seq: Path) -> None:
    proc = nislam("bench", str(fixture_seq), "--json", "--max-frames", "8")
    assert proc.returncode == 0, proc.stderr
    stats = json.loads(proc.stdout)  # raises if stdout holds anything else
    assert isinstance(stats, dict) and BENCH_KEYS <= set(stats)
    assert stats["frames"] == 8
    assert stats["hz"] == pytest.approx(1000.0 / stats["frame_ms_median"])
    assert stats["frame_ms_median"] <= stats["frame_ms_p95"] <= stats["frame_ms_max"]


def test_bench_times_fastorbs_back_end_apart(fixture_seq: Path) -> None:
    """FastORB's loop closing runs after the frames (backend_step): the bench
    times each key frame's query there, apart from tracking, one per key
    frame, and prints it; --no-loop-closure leaves none."""
    proc = nislam("bench", str(fixture_seq), "--tracker", "fastorb", "--json")
    assert proc.returncode == 0, proc.stderr
    stats = json.loads(proc.stdout)
    assert stats["keyframe_frames"] >= 1
    assert stats["loop_queries"] == stats["keyframe_frames"]
    assert stats["backend_slices"] >= stats["loop_queries"]
    assert 0.0 < stats["loop_query_ms_median"] <= stats["loop_query_ms_p95"]
    # A key frame's making runs after its pose (finish_frame), timed apart;
    # the thread's CPU time is reported beside the wall time.
    assert stats["keyframe_deferred_ms_median"] > 0.0
    assert 0.0 < stats["cpu_ms_median"] <= stats["cpu_ms_p95"]
    text = nislam("bench", str(fixture_seq), "--tracker", "fastorb").stdout
    assert "loop closing per key frame" in text and "CPU time per frame" in text
    off = json.loads(nislam("bench", str(fixture_seq), "--tracker", "fastorb", "--json",
                            "--no-loop-closure").stdout)
    assert off["loop_queries"] == 0 and off["loop_query_ms_median"] is None


def test_missing_sequence_is_one_line_exit_1(tmp_path: Path) -> None:
    proc = nislam("replay", str(tmp_path / "nope"), "--out", str(tmp_path / "out"))
    assert proc.returncode == 1
    assert proc.stderr.strip().count("\n") == 0
    assert proc.stderr.startswith("nislam: error: ") and "nope" in proc.stderr
    assert not (tmp_path / "out").exists()


def test_bad_config_key_exit_1_names_key(fixture_seq: Path, tmp_path: Path) -> None:
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[nislam]\ngrid_widht = 100\n")
    proc = nislam("replay", str(fixture_seq), "--config", str(cfg), "--out", str(tmp_path))
    assert proc.returncode == 1
    assert proc.stderr.strip() == f"nislam: error: {cfg}: unknown key 'nislam.grid_widht'"


def test_unknown_tracker_exit_1(fixture_seq: Path, tmp_path: Path) -> None:
    proc = nislam("bench", str(fixture_seq), "--tracker", "nope", "--json")
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.startswith("nislam: error: ") and "'nope'" in proc.stderr
    assert proc.stderr.strip().count("\n") == 0


def test_fastorb_replay_tracks_the_fixture(fixture_seq: Path, tmp_path: Path) -> None:
    """`--tracker fastorb` runs end to end: every fixture frame posed, scored."""
    out = tmp_path / "out"
    proc = nislam("replay", str(fixture_seq), "--tracker", "fastorb", "--out", str(out),
                  "--quiet")
    assert proc.returncode == 0, proc.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames_tracked"] == metrics["frames"] > 0
    assert metrics["ate_rmse_m"] < 0.05
    # loop closing ran (on by default) and the final trajectory was scored
    assert metrics["loops_detected"] is not None and metrics["ate_final_rmse_m"] < 0.05


def test_replay_without_groundtruth(fixture_seq: Path, tmp_path: Path) -> None:
    """Attitude from attitude.txt, no groundtruth.txt: no ATE/RPE, no plot, and
    a ground-truth file left by an earlier run is removed, not kept stale."""
    seq = tmp_path / "tum_fr3_no_gt"
    shutil.copytree(fixture_seq, seq)
    gt_lines = (seq / "groundtruth.txt").read_text().splitlines()
    rows = [ln.split() for ln in gt_lines if ln.strip() and not ln.startswith("#")]
    (seq / "attitude.txt").write_text("".join(f"{r[0]} {' '.join(r[4:8])}\n" for r in rows))
    (seq / "groundtruth.txt").unlink()
    out = tmp_path / "out"
    out.mkdir()
    (out / "groundtruth_at_frames.tum").write_text("stale")

    result = replay(seq, Config(), out, progress=False)
    assert result.metrics["ate_rmse_m"] is None and result.metrics["rpe_trans_rmse_m"] is None
    assert result.metrics["frames"] == FIXTURE_FRAMES
    assert result.metrics["attitude_source"].startswith("attitude.txt")
    text = "\n".join(result.summary_lines())
    assert "no ground truth" in text and "plot        skipped" in text
    assert not (out / "groundtruth_at_frames.tum").exists()
    assert not (out / "trajectory.png").exists()
    assert len(read_tum(out / "trajectory.tum")) == result.metrics["frames_tracked"]


def test_verbose_flag_before_or_after_the_command() -> None:
    from onboard.app.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["-vv", "bench"]).verbose == 2
    assert parser.parse_args(["bench", "-v"]).verbose == 1
    assert getattr(parser.parse_args(["bench"]), "verbose", 0) == 0


@pytest.mark.parametrize(("exc", "code"), [(KeyboardInterrupt, 130), (RuntimeError, 2)])
def test_exit_codes_for_interrupt_and_bugs(monkeypatch, capsys, tmp_path, exc, code) -> None:
    import onboard.app.replay
    from onboard.app.cli import main

    def boom(*_args, **_kwargs):
        raise exc("boom")

    monkeypatch.setattr(onboard.app.replay, "replay", boom)
    root = logging.getLogger()
    # main() installs its own stderr handler; give pytest's back afterwards.
    monkeypatch.setattr(root, "handlers", list(root.handlers))
    level = root.level
    try:
        assert main(["replay", str(tmp_path), "--quiet"]) == code
    finally:
        root.setLevel(level)
    err = capsys.readouterr().err
    if code == 2:
        assert "Traceback" in err and "RuntimeError: boom" in err
    else:
        assert err.strip() == "nislam: error: interrupted"
