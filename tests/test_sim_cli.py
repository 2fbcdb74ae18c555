"""`nislam sim` and `nislam faults` as a user runs them (subprocess)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from sim_replay.fault_plan import KINDS
from sim_replay.flights import SCENARIOS
from sim_replay.sim import SIM_MANIFEST

REPO = Path(__file__).resolve().parents[1]


def nislam(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    return subprocess.run([sys.executable, "-m", "onboard.app.cli", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=300)


def test_sim_then_faults_end_to_end(tmp_path):
    out = tmp_path / "hover"
    proc = nislam("sim", "hover", "--seconds", "1", "--width", "64", "--height", "48",
                  "--out", str(out), "--seed", "3", "--ahrs-profile", "myahrs",
                  "--attitude-noise-deg", "0.3", "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert "frames      30 colour + depth" in proc.stdout and "frames/s on one core" in proc.stdout
    manifest = json.loads((out / SIM_MANIFEST).read_text())
    errors = manifest["options"]["ahrs"]["errors"]
    # The profile sets the model, an explicit flag overrides its term.
    assert errors["noise_deg"] == 0.3 and errors["offset_ms"] == 5.0
    assert manifest["options"]["ahrs"]["dropout"] == 0.005 and manifest["options"]["seed"] == 3
    assert len((out / "rgb.txt").read_text().splitlines()) == 32  # 2 comments + 30 frames

    bad = tmp_path / "bad"
    proc = nislam("faults", str(out), "--out", str(bad), "--faults", "drop:2,att-nan:1")
    assert proc.returncode == 0, proc.stderr
    assert "dropped_frames +2" in proc.stdout and "attitude_nan_samples +1" in proc.stdout
    assert json.loads((bad / "faults.json").read_text())["spec"] == "drop:2,att-nan:1"


def test_errors_are_one_line_and_exit_1(tmp_path):
    for args, message in [
        (("sim", "barrel-roll", "--out", str(tmp_path / "a")), "unknown scenario 'barrel-roll'"),
        (("sim", "hover", "--out", str(tmp_path / "b"), "--faults", "drop:0"), "whole number"),
        (("sim", "hover", "--out", str(tmp_path / "c"), "--ahrs-profile", "x"), "AHRS profile"),
        (("faults", str(tmp_path / "none"), "--out", str(tmp_path / "d"), "--faults", "drop"),
         "not a TUM-layout recording"),
    ]:
        proc = nislam(*args)
        assert proc.returncode == 1, (args, proc.stderr)
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("nislam: error:") and message in lines[0]


def test_help_lists_every_scenario_and_fault_kind():
    text = nislam("sim", "--help").stdout
    for name in SCENARIOS:
        assert name in text
    for kind in KINDS:
        assert f"  {kind}:" in text
    assert "--faults SPEC" in nislam("faults", "--help").stdout
