"""`nislam doctor` on a machine with no camera (the fake depthai finds no
device: no real device search here) and a missing AHRS port: exit 1, one row
each naming the OAK-D and the AHRS port with the cause."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent / "peers"))

from fake_depthai import FakeDai  # noqa: E402

from onboard.app import doctor  # noqa: E402
from onboard.app.config import load_config  # noqa: E402


def test_doctor_without_camera_and_ahrs_fails_with_one_row_each(tmp_path, monkeypatch, capsys):
    dai = FakeDai(fail_opens=10**6)
    monkeypatch.setattr("drivers.oak.import_depthai", lambda: dai)
    port = tmp_path / "ttyAHRS"
    toml = tmp_path / "vehicle.toml"
    toml.write_text(f'[ahrs]\nsource = "myahrs"\n[myahrs]\nport = "{port}"\n')
    from onboard.app.cli import main

    assert main(["doctor", "--config", str(toml), "--wait", "1"]) == 1
    out = capsys.readouterr().out.splitlines()
    cam = [ln for ln in out if ln.startswith("camera (OAK-D)")]
    ahrs = [ln for ln in out if ln.startswith("ahrs (myAHRS+)")]
    assert len(cam) == 1 and "FAIL" in cam[0] and "no device" in cam[0] and "no OAK device" in cam[0]
    assert len(ahrs) == 1 and "FAIL" in ahrs[0] and str(port) in ahrs[0]
    assert "No such file or directory" in ahrs[0]
    fixes = [ln for ln in out if ln.strip().startswith("fix:")]
    assert any("OAK-D" in f for f in fixes) and any(str(port) in f for f in fixes)
    assert out[-1].startswith("2 of") and "camera (OAK-D), ahrs (myAHRS+)" in out[-1]


def test_doctor_passes_with_the_devices_there(tmp_path):
    cfg = load_config(None, {"ahrs.source": "oak_imu", "oak.width": 64, "oak.height": 48,
                             "oak.mono_width": 64, "oak.mono_height": 48})
    checks = doctor.run_checks(cfg, dai_loader=lambda: FakeDai(), out_dir=tmp_path, wait_s=1.0,
                               wall_clock=lambda: 0.0)  # a board without RTC: 1970
    by = {c.name: c for c in checks}
    assert by["camera (OAK-D)"].status in ("ok", "warn") and "64x48" in by["camera (OAK-D)"].detail
    assert by["ahrs (OAK-D IMU)"].status == "ok"
    assert by["clock"].status == "warn" and "1970" in by["clock"].detail
    assert not [c for c in checks if c.status == "FAIL"]
