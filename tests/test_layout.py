"""The floor plan (docs/architecture.md) holds: import contracts that fail
when broken, no module over 500 lines, a small onboard/ top level and a
user-sized README."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("onboard", "drivers", "sim_replay")
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")


def _lint_imports(root: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(root))  # grimp finds this tree's packages first
    return subprocess.run([str(LINT_IMPORTS), "--config", str(root / "pyproject.toml"),
                           "--no-cache"], cwd=root, env=env, capture_output=True, text=True,
                          timeout=300)


def _copy_tree(dst: Path) -> Path:
    shutil.copy(REPO / "pyproject.toml", dst / "pyproject.toml")
    for pkg in PACKAGES:
        shutil.copytree(REPO / pkg, dst / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    return dst


def test_import_contracts_hold() -> None:
    proc = _lint_imports(REPO)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "broken" not in proc.stdout.split("Contracts:")[-1].split("\n")[0].replace(
        "0 broken", "")


@pytest.mark.parametrize(("module", "line", "contract"), [
    # rule 3: the trackers are pure
    ("onboard/nislam/tracker.py", "import zenoh", "are pure"),
    # rule 2: drivers and replays never import each other
    ("drivers/oak.py", "import sim_replay.tum", "never import each other"),
    # rule 1: no cycle (the core imports the app that imports it)
    ("onboard/core/messages.py", "import onboard.app.config", "No import cycle"),
])
def test_a_broken_rule_fails_the_check(tmp_path: Path, module: str, line: str,
                                       contract: str) -> None:
    root = _copy_tree(tmp_path)
    path = root / module
    path.write_text(path.read_text() + f"\n{line}  # breaks the architecture\n")
    proc = _lint_imports(root)
    assert proc.returncode != 0
    broken = [ln for ln in proc.stdout.splitlines() if ln.endswith("BROKEN")]
    assert any(contract in ln for ln in broken) or contract in proc.stdout.split(
        "Broken contracts")[-1], proc.stdout


def test_no_module_over_500_lines() -> None:
    long = {str(p.relative_to(REPO)): n for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 500}
    assert not long


def test_onboard_top_level_is_packages_and_at_most_8_modules() -> None:
    modules = sorted(p.name for p in (REPO / "onboard").glob("*.py"))
    assert len(modules) <= 8, modules
    packages = {p.name for p in (REPO / "onboard").iterdir() if (p / "__init__.py").is_file()}
    assert {"core", "nislam", "fastorb", "fusion", "outputs", "app"} <= packages


def test_readme_is_short_and_links_the_docs() -> None:
    readme = (REPO / "README.md").read_text()
    assert len(readme.encode()) <= 20_000
    linked = [p for p in (REPO / "docs").glob("*.md") if f"docs/{p.name}" in readme]
    assert len(linked) >= 5, linked
