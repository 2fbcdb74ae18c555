"""Reading the configuration (and so `nislam --help`, a config check) does not
load the trackers: their numba kernels and cv2 load in the registry's
builders (onboard/fusion/registry.py)."""

from __future__ import annotations

import subprocess
import sys


def test_the_configuration_loads_no_tracker():
    code = ("import sys, onboard.app.config as c; c.load_config(None, {}); "
            "print(sorted(m for m in ('numba', 'onboard.nislam.tracker', "
            "'onboard.fastorb.tracker', 'onboard.fusion.fused') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_the_registry_still_builds_every_tracker():
    from onboard.app.config import load_config
    from onboard.core.camera import CameraIntrinsics
    from onboard.fusion.registry import TRACKER_NAMES, make_tracker

    cfg = load_config(None, {})
    k = CameraIntrinsics(fx=50.0, fy=50.0, cx=32.0, cy=24.0, width=64, height=48)
    for name in TRACKER_NAMES:
        assert make_tracker(name, k, cfg) is not None, name
