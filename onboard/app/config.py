"""Typed configuration: defaults in code, overrides from a TOML file and the CLI.

Sections map one-to-one onto frozen dataclasses: `[replay]` -> ReplayConfig,
`[attitude]` -> AttitudeErrorConfig, `[tracker]` -> TrackerConfig,
`[nislam]` / `[fastorb]` -> the trackers' own `NislamParams` / `FastOrbParams`,
`[fusion]` -> `FusionParams` (the fused tracker),
`[mavlink]` -> MavlinkConfig
`[zenoh]` -> ZenohConfig (the outputs) and `[router]` -> RouterConfig
(`nislam router`); `[ahrs]`, `[myahrs]`,
`[autopilot]`, `[oak]` and `[record]` -> the driver and recording sections
(AhrsConfig ... RecordConfig); `[service]` -> ServiceConfig (`nislam run`);
`[sim_follow]` -> SimFollowConfig (`nislam run --sim-follow`).
The `[nislam]` and `[fastorb]` keys are read
from those dataclasses' fields, so a parameter added to a tracker is
configurable (and validated by its type) without touching this module.

Every bad key stops the load with one `NislamError` line naming the key: an
unknown key, a value of the wrong type or one outside its range.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import sys
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import tomli_w

from onboard import NislamError, __version__
from onboard.app.config_rules import DEFAULT_RULES, ORDERED, RULES
from onboard.app.config_sections import (
    AhrsConfig,
    AttitudeErrorConfig,
    AutopilotConfig,
    MyAhrsConfig,
    OakConfig,
    RecordConfig,
    ReplayConfig,
    ServiceConfig,
    SimFollowConfig,
    TrackerConfig,
)
from onboard.fastorb.params import FastOrbParams
from onboard.fusion.params import FusionParams
from onboard.fusion.registry import resolve_name
from onboard.nislam.params import NislamParams
from onboard.outputs.settings import MavlinkConfig, RouterConfig, ZenohConfig

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - pyproject pulls tomli in for 3.10
    import tomli as tomllib

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Config:
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    attitude: AttitudeErrorConfig = field(default_factory=AttitudeErrorConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    nislam: NislamParams = field(default_factory=NislamParams)
    fastorb: FastOrbParams = field(default_factory=FastOrbParams)
    fusion: FusionParams = field(default_factory=FusionParams)
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    router: RouterConfig = field(default_factory=RouterConfig)
    ahrs: AhrsConfig = field(default_factory=AhrsConfig)
    myahrs: MyAhrsConfig = field(default_factory=MyAhrsConfig)
    autopilot: AutopilotConfig = field(default_factory=AutopilotConfig)
    oak: OakConfig = field(default_factory=OakConfig)
    record: RecordConfig = field(default_factory=RecordConfig)
    service: ServiceConfig = field(default_factory=ServiceConfig)
    sim_follow: SimFollowConfig = field(default_factory=SimFollowConfig)


SECTIONS: dict[str, type] = {
    "replay": ReplayConfig,
    "attitude": AttitudeErrorConfig,
    "tracker": TrackerConfig,
    "nislam": NislamParams,
    "fastorb": FastOrbParams,
    "fusion": FusionParams,
    "mavlink": MavlinkConfig,
    "zenoh": ZenohConfig,
    "router": RouterConfig,
    "ahrs": AhrsConfig,
    "myahrs": MyAhrsConfig,
    "autopilot": AutopilotConfig,
    "oak": OakConfig,
    "record": RecordConfig,
    "service": ServiceConfig,
    "sim_follow": SimFollowConfig,
}


# --------------------------------------------------------------------------- rules


# --------------------------------------------------------------------------- loading


def load_config(
    path: Path | str | None = None,
    overrides: Mapping[str, Any] | None = None,
    overrides_origin: str = "overrides",
) -> Config:
    """Defaults, then the TOML file at `path`, then `overrides`.

    `overrides` maps qualified keys to values, e.g. {"attitude.noise_deg": 1.0};
    `overrides_origin` names them in error messages (e.g. "command line").
    Raises NislamError naming the offending key.
    """
    values: dict[str, dict[str, Any]] = {name: {} for name in SECTIONS}
    if path is not None:
        origin = str(path)
        for key, value in _flatten(_read_toml(Path(path)), origin).items():
            _set(values, key, value, origin)
    for key, value in (overrides or {}).items():
        _set(values, key, value, overrides_origin)
    cfg = Config(**{name: SECTIONS[name](**values[name]) for name in SECTIONS})
    _check_order(cfg, str(path) if path is not None else "config")
    log.debug("effective config:\n%s", config_to_toml(cfg))
    return cfg


def with_tracker_resolved(cfg: Config, service: bool) -> Config:
    """`cfg` with `[tracker] name = "auto"` replaced by the tracker the command
    runs (the onboard loop, `service`: fused; replay and bench: NI-SLAM), so
    the configuration written beside a result names the tracker that made it."""
    name = resolve_name(cfg.tracker.name, service)
    if name == cfg.tracker.name:
        return cfg
    return dataclasses.replace(cfg, tracker=dataclasses.replace(cfg.tracker, name=name))


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise NislamError(f"{path}: config file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise NislamError(f"{path}: cannot read config: {e}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise NislamError(f"{path}: not valid TOML: {e}") from None


def _flatten(raw: dict[str, Any], origin: str) -> dict[str, Any]:
    """{section: {key: value}} -> {"section.key": value}."""
    flat: dict[str, Any] = {}
    for section, table in raw.items():
        if section not in SECTIONS:
            raise NislamError(
                f"{origin}: unknown section '{section}' (known: {', '.join(SECTIONS)})"
            )
        if not isinstance(table, dict):
            raise NislamError(f"{origin}: '{section}' must be a table ([{section}])")
        for key, value in table.items():
            flat[f"{section}.{key}"] = value
    return flat


def _set(values: dict[str, dict[str, Any]], key: str, value: Any, origin: str) -> None:
    section, _, name = key.partition(".")
    types = _field_types(SECTIONS[section]) if section in SECTIONS else {}
    if name not in types:
        raise NislamError(f"{origin}: unknown key '{key}'")
    checked = _check_type(key, value, types[name], origin)
    rule = RULES.get(key) or DEFAULT_RULES.get(type(checked))
    problem = rule.violation(checked) if rule is not None else None
    if problem is not None:
        raise NislamError(f"{origin}: '{key}' {problem}, got {checked!r}")
    values[section][name] = checked


def _field_types(cls: type) -> dict[str, Any]:
    # get_type_hints resolves the string annotations of `from __future__ import annotations`.
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


_TYPE_WORDS = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}


def _check_type(key: str, value: Any, tp: Any, origin: str) -> Any:
    """The value converted to the field's type (int -> float), or NislamError."""
    if tp in _TYPE_WORDS:
        ok = _scalar(value, tp)
        if ok is None:
            raise NislamError(
                f"{origin}: '{key}' must be {_TYPE_WORDS[tp]}, got {_toml_type(value)}"
            )
        return ok
    if typing.get_origin(tp) is tuple:
        args = typing.get_args(tp)
        item = args[0] if args else Any
        items = [_scalar(v, item) for v in value] if isinstance(value, list) else None
        if items is None or any(v is None for v in items):
            raise NislamError(
                f"{origin}: '{key}' must be an array of {getattr(item, '__name__', item)} values"
            )
        if len(args) >= 2 and args[1] is not Ellipsis and len(items) != len(args):
            raise NislamError(f"{origin}: '{key}' must hold {len(args)} values, got {len(items)}")
        return tuple(items)
    raise NislamError(f"{origin}: '{key}' has type {tp} that a config file cannot set")


def _scalar(value: Any, tp: Any) -> Any:
    """`value` as `tp`, or None. bool is an int subclass in Python, but
    `grid_width = true` is a typo, not 1; an int is a fine float."""
    if tp is bool:
        return value if isinstance(value, bool) else None
    if isinstance(value, bool):
        return None
    if tp is int:
        return value if isinstance(value, int) else None
    if tp is float:
        if isinstance(value, (int, float)) and math.isfinite(value):
            return float(value)
        return None
    if tp is str:
        return value if isinstance(value, str) else None
    return None


def _toml_type(value: Any) -> str:
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)
    return type(value).__name__


def _check_order(cfg: Config, origin: str) -> None:
    for lo_key, hi_key in ORDERED:
        lo, hi = _get(cfg, lo_key), _get(cfg, hi_key)
        if lo is not None and hi is not None and not lo < hi:
            raise NislamError(f"{origin}: '{lo_key}' ({lo:g}) must be < '{hi_key}' ({hi:g})")


def _get(cfg: Config, key: str) -> Any:
    section, _, name = key.partition(".")
    return getattr(getattr(cfg, section), name, None)


# --------------------------------------------------------------------------- writing


def config_to_dict(cfg: Config) -> dict[str, dict[str, Any]]:
    """Every value of every section, TOML-ready (tuples as lists)."""
    out: dict[str, dict[str, Any]] = {}
    for section in SECTIONS:
        obj = getattr(cfg, section)
        out[section] = {
            f.name: _to_toml(getattr(obj, f.name)) for f in dataclasses.fields(obj)
        }
    return out


def config_to_toml(cfg: Config) -> str:
    """The effective config as TOML; `load_config` of it gives `cfg` back."""
    header = f"# Effective configuration (nislam-onboard {__version__}): every value used.\n\n"
    return header + tomli_w.dumps(config_to_dict(cfg))


def _to_toml(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value
