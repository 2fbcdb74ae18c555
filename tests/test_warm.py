"""`python -m onboard.app.warm` (the last step of `make venv`) leaves no
numba kernel to compile on the pose's path."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# A fresh interpreter: in this one other tests may have compiled already
# what the warm-up misses.
SCRIPT = """
import json, sys
from onboard.app import warm
from onboard.app.bench import bench
from onboard.app.config import load_config
warm.warm_up()
before = warm.compiled_signatures()
bench(sys.argv[1], load_config(None, {"tracker.name": "fused"}), 40)
after = warm.compiled_signatures()
print(json.dumps({"kernels": len(after), "new": {k: after[k] - before[k] for k in after
                                                   if after[k] != before[k]}}))
"""


def test_the_warm_up_compiles_every_signature_the_trackers_use(shared_data: Path) -> None:
    """Both trackers (the fused one runs NI-SLAM and FastORB) over the first
    40 frames of tum_fr1_rpy, whose rolling shutter bends NI-SLAM's rays
    into a writable array and whose LK pixels reach FastORB's depth look-up
    as float32: no kernel gains a signature after the warm-up (each would
    be compiled on the first frame that needs it, ~0.5-1 s on the pose's
    path, and again after every upgrade)."""
    out = subprocess.run([sys.executable, "-c", SCRIPT, str(shared_data / "tum_fr1_rpy")],
                         cwd=REPO, capture_output=True, text=True, timeout=600, check=True)
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["kernels"] >= 20  # every module's kernels were found
    assert got["new"] == {}
