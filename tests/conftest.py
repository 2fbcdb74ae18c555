"""Shared pytest fixtures."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import tempfile
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

# The MAVLink feed keeps its last reset_counter under the service's state
# directory ($XDG_STATE_HOME/nislam by default) and --sim-follow its scene's
# textures in the cache directory: tests and the services they start keep
# theirs in temporary folders, never in the user's home.
os.environ["XDG_STATE_HOME"] = tempfile.mkdtemp(prefix="nislam-test-state-")
os.environ["XDG_CACHE_HOME"] = tempfile.mkdtemp(prefix="nislam-test-cache-")  # textures
os.environ.pop("CACHE_DIRECTORY", None)
os.environ.pop("STATE_DIRECTORY", None)

# In CI the repository is cloned with `shared/` beside it: <repo>/../shared/data.
SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

EvoRunner = Callable[[str, list[str]], tuple[dict, np.ndarray]]


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The recorded-data folder; skips the test when it is not checked out."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared test data not found at {SHARED_DATA} (expected <repo>/../shared/data)")
    return SHARED_DATA


def run_evo(tool: str, args: list[str], tmp_path: Path) -> tuple[dict, np.ndarray]:
    """Run an evo CLI tool; returns (stats.json, error_array) from --save_results."""
    exe = Path(sys.executable).parent / tool
    if not exe.exists():
        pytest.skip(f"{tool} not installed")
    zip_path = tmp_path / f"{tool}_{abs(hash(tuple(args)))}.zip"
    # evo writes ~/.evo/settings.json on first run and may try a GUI backend.
    env = dict(os.environ, HOME=str(tmp_path), MPLBACKEND="Agg")
    proc = subprocess.run(
        [str(exe), *args, "--save_results", str(zip_path), "--no_warnings"],
        env=env, cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    with zipfile.ZipFile(zip_path) as z:
        stats = json.loads(z.read("stats.json"))
        errors = np.load(io.BytesIO(z.read("error_array.npy")))
    return stats, errors


@pytest.fixture()
def evo(tmp_path: Path) -> EvoRunner:
    """`evo(tool, args)` runs an evo CLI tool in this test's tmp_path (see run_evo)."""
    return lambda tool, args: run_evo(tool, args, tmp_path)
