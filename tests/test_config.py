"""Config loading: defaults, validation messages naming the key, overrides, round trip."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import pytest

from onboard import NislamError
from onboard.app.config import (
    SECTIONS,
    Config,
    config_to_dict,
    config_to_toml,
    load_config,
    with_tracker_resolved,
)
from onboard.app.config_rules import RULES
from onboard.fusion.registry import TRACKER_NAMES, make_tracker
from onboard.nislam.params import NislamParams

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

CONFIG_DIR = Path(__file__).resolve().parents[1] / "config"


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "x.toml"
    path.write_text(text)
    return path


def _error(path: Path | None = None, overrides: dict | None = None) -> str:
    with pytest.raises(NislamError) as exc:
        load_config(path, overrides)
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


def test_defaults_without_file() -> None:
    cfg = load_config(None, {})
    assert cfg == Config()
    assert cfg.nislam == NislamParams()
    assert cfg.replay.assoc_max_dt_s == 0.02 and cfg.replay.gt_max_gap_s == 0.2
    assert cfg.tracker.name == "auto"


def test_auto_tracker_is_each_commands_own() -> None:
    """`[tracker] name = "auto"` (the default): the onboard loop flies on the
    fused tracker, replay and bench measure NI-SLAM; a name given is kept."""
    auto = Config()
    assert with_tracker_resolved(auto, service=True).tracker.name == "fused"
    assert with_tracker_resolved(auto, service=False).tracker.name == "nislam"
    for name in TRACKER_NAMES:
        given = load_config(None, {"tracker.name": name})
        assert with_tracker_resolved(given, service=True).tracker.name == name
        assert with_tracker_resolved(given, service=False).tracker.name == name
    # Resolved, the rest of the configuration is untouched.
    assert dataclasses.replace(with_tracker_resolved(auto, service=True), tracker=auto.tracker) == auto


def test_unknown_key_is_named(tmp_path: Path) -> None:
    path = _write(tmp_path, "[nislam]\ngrid_widht = 10\n")
    msg = _error(path)
    assert msg == f"{path}: unknown key 'nislam.grid_widht'"


def test_unknown_section_is_named(tmp_path: Path) -> None:
    msg = _error(_write(tmp_path, "[nislamm]\ngrid_width = 10\n"))
    assert "unknown section 'nislamm'" in msg


def test_top_level_key_is_rejected(tmp_path: Path) -> None:
    assert "'lam'" in _error(_write(tmp_path, "lam = 0.1\n"))


@pytest.mark.parametrize(
    ("toml", "expected"),
    [
        ('[nislam]\nlam = "0.1"\n', "'nislam.lam' must be a number, got str"),
        ("[nislam]\ngrid_width = 480.0\n", "'nislam.grid_width' must be an integer, got float"),
        # bool is an int in Python, but not a grid size.
        ("[nislam]\ngrid_width = true\n", "'nislam.grid_width' must be an integer, got bool"),
        ("[nislam]\nlam = true\n", "'nislam.lam' must be a number, got bool"),
        ("[replay]\nundistort = 1\n", "'replay.undistort' must be true or false, got int"),
        ("[tracker]\nname = 3\n", "'tracker.name' must be a string, got int"),
        ("[nislam]\nlam = nan\n", "'nislam.lam' must be a number, got nan"),
        ("[nislam]\nlam = [0.1]\n", "'nislam.lam' must be a number, got list"),
    ],
)
def test_wrong_type_is_named(tmp_path: Path, toml: str, expected: str) -> None:
    assert _error(_write(tmp_path, toml)).endswith(expected)


@pytest.mark.parametrize(
    ("toml", "expected"),
    [
        ("[nislam]\ngrid_width = 0\n", "'nislam.grid_width' must be > 0, got 0"),
        ("[nislam]\nadaptive_mu = 1.5\n", "'nislam.adaptive_mu' must be in (0, 1], got 1.5"),
        ("[nislam]\nadaptive_mu = 0\n", "'nislam.adaptive_mu' must be in (0, 1], got 0.0"),
        ("[nislam]\npsr_lost = -1.0\n", "'nislam.psr_lost' must be >= 0, got -1.0"),
        ("[attitude]\nnoise_deg = -0.5\n", "'attitude.noise_deg' must be >= 0, got -0.5"),
        ("[attitude]\nseed = -1\n", "'attitude.seed' must be >= 0, got -1"),
        ("[tracker]\nname = \"orb\"\n", "'tracker.name' must be one of 'auto', 'nislam', 'fastorb', 'fused'"),
        (
            "[nislam]\nmin_depth_m = 7.0\n",
            "'nislam.min_depth_m' (7) must be < 'nislam.max_depth_m'",
        ),
    ],
)
def test_impossible_value_is_named(tmp_path: Path, toml: str, expected: str) -> None:
    assert expected in _error(_write(tmp_path, toml))


def test_int_is_accepted_for_float(tmp_path: Path) -> None:
    cfg = load_config(_write(tmp_path, "[nislam]\nlam = 1\n"))
    assert cfg.nislam.lam == 1.0 and isinstance(cfg.nislam.lam, float)


def test_missing_and_invalid_files(tmp_path: Path) -> None:
    assert "not found" in _error(tmp_path / "nope.toml")
    assert "not valid TOML" in _error(_write(tmp_path, "[nislam\n"))


def test_overrides_beat_the_file(tmp_path: Path) -> None:
    path = _write(tmp_path, "[attitude]\nnoise_deg = 2.0\nseed = 3\n")
    cfg = load_config(
        path, {"attitude.noise_deg": 1, "nislam.calibrate_time_offset": False}
    )
    assert cfg.attitude.noise_deg == 1.0 and cfg.attitude.seed == 3
    assert cfg.nislam.calibrate_time_offset is False
    assert cfg.nislam.grid_width == NislamParams().grid_width


def test_bad_override_is_named() -> None:
    msg = _error(None, {"nislam.grid_widht": 3})
    assert "unknown key 'nislam.grid_widht'" in msg
    assert "'attitude.noise_deg' must be >= 0" in _error(None, {"attitude.noise_deg": -1.0})
    with pytest.raises(NislamError, match="^command line: unknown key 'bogus'"):
        load_config(None, {"bogus": 1}, overrides_origin="command line")


def test_round_trip_is_exact(tmp_path: Path) -> None:
    cfg = load_config(
        None,
        {"nislam.lam": 0.123456789012345, "attitude.offset_ms": -20.0, "replay.undistort": False},
    )
    path = tmp_path / "config.toml"
    path.write_text(config_to_toml(cfg))
    assert load_config(path) == cfg
    # Every field of every section is written, not only the changed ones.
    written = tomllib.loads(path.read_text())
    for section, cls in SECTIONS.items():
        assert set(written[section]) == {f.name for f in dataclasses.fields(cls)}


def test_rule_table_names_real_fields() -> None:
    """A renamed tracker parameter must not leave a dead range rule behind."""
    fields = {
        f"{section}.{f.name}" for section, cls in SECTIONS.items() for f in dataclasses.fields(cls)
    }
    assert set(RULES) <= fields, sorted(set(RULES) - fields)


def test_every_default_passes_its_rule() -> None:
    flat = {
        f"{s}.{k}": v for s, table in config_to_dict(Config()).items() for k, v in table.items()
    }
    assert load_config(None, flat) == Config()


def test_default_toml_lists_every_key_with_its_default() -> None:
    """config/default.toml documents the code's defaults: a parameter added or
    retuned in code must be added or updated there too."""
    path = CONFIG_DIR / "default.toml"
    written = tomllib.loads(path.read_text())
    expected = config_to_dict(Config())
    for section, table in expected.items():
        assert set(written.get(section, {})) == set(table), f"[{section}] in {path}"
        differ = {k: (written[section][k], v) for k, v in table.items() if written[section][k] != v}
        assert not differ, f"[{section}] in {path}: (file, code) = {differ}"


def test_profiles_load() -> None:
    for path in sorted(CONFIG_DIR.glob("*.toml")):
        load_config(path)


def test_tracker_factory() -> None:
    from onboard.core.camera import CameraIntrinsics

    intr = CameraIntrinsics(500.0, 500.0, 320.0, 240.0, 640, 480)
    tracker = make_tracker("nislam", intr, Config())
    assert tracker.name == "nislam"
    assert "fastorb" in TRACKER_NAMES
    assert make_tracker("fastorb", intr, Config()).name == "fastorb"
    with pytest.raises(NislamError, match="unknown tracker 'nope'"):
        make_tracker("nope", intr, Config())
