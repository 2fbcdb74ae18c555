"""The one registry of trackers: the names the configuration accepts
(`[tracker] name`, `--tracker`) and the factory that builds one.

Every tracker is a pure core (arrays in, a result out) behind the same
`onboard.core.messages.Tracker` protocol, so replay, bench and the onboard loop
never ask which one they hold. The factory reads each tracker's parameters from
its own section of the configuration (`[nislam]`, `[fastorb]`, `[fusion]`); it takes any
object carrying those sections, so this module needs nothing of the
application's configuration (which reads `TRACKER_NAMES` from here).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any, Protocol

from onboard import NislamError
from onboard.core.camera import CameraIntrinsics
from onboard.core.messages import Tracker
from onboard.fastorb.params import FastOrbParams
from onboard.fusion.params import FusionParams
from onboard.nislam.params import NislamParams

# The trackers themselves (numba kernels, cv2) load in their builders: the
# configuration reads TRACKER_NAMES from here, and `nislam --help` or a
# config check should not pay for compiling machinery it never runs.


class TrackerSections(Protocol):
    """The trackers' configuration sections (onboard.app.config.Config has them)."""

    @property
    def nislam(self) -> NislamParams: ...

    @property
    def fastorb(self) -> FastOrbParams: ...


def _make_nislam(intrinsics: CameraIntrinsics, cfg: TrackerSections, **overrides: Any) -> Tracker:
    """`overrides`: NislamParams fields the caller fixes whatever the config says."""
    from onboard.nislam.tracker import NislamTracker

    # Noise a replay adds to the attitude (`--attitude-noise-deg`, [attitude]
    # noise_deg) comes on top of the AHRS's own: independent, in quadrature.
    params = cfg.nislam
    added = getattr(getattr(cfg, "attitude", None), "noise_deg", 0.0)
    if added > 0.0:
        overrides.setdefault("attitude_sd_deg", math.hypot(params.attitude_sd_deg, added))
    return NislamTracker(intrinsics, dataclasses.replace(params, **overrides))


def _make_fastorb(intrinsics: CameraIntrinsics, cfg: TrackerSections, **overrides: Any) -> Tracker:
    """`overrides`: FastOrbParams fields the caller fixes whatever the config says."""
    from onboard.fastorb.tracker import FastOrbTracker

    return FastOrbTracker(intrinsics, dataclasses.replace(cfg.fastorb, **overrides))


def fused_parts(intrinsics: CameraIntrinsics, cfg: TrackerSections) -> list[Tracker]:
    """The fused tracker's parts, NI-SLAM first (its key-frame clouds make the
    map, onboard.fusion.fused), as it builds them: also what
    scripts/fusion_cache.py records."""
    # The filter clones a key's fused position at the frame that announces it
    # (onboard.fusion.fused) and NI-SLAM's own key positions never reach the
    # output, so its keys stay at the paper's frame (Eq. 17) whatever the setting.
    # Its Eq. 18 stays the paper's too (the refined key, every 2nd pixel): its
    # covariance model was set on that, and with the key at every pixel the
    # fused ATE rose on `corridor` (4.1 -> 8.5 mm) and `blank-turn` (6.7 ->
    # 8.7 mm) while NI-SLAM alone gained (docs/nislam-error-budget.md, "A key's
    # depth from every pixel").
    nislam = _make_nislam(intrinsics, cfg, key_from_last_firm_frame=False, key_depth_stride=0,
                          depth_front_mean_m=0.0)
    # The filter closes its loops on NI-SLAM's key clones. FastORB's own loop
    # closing would move its world under the filter (a correction is never
    # motion: docs/fusion.md), and its records of every key frame grow with
    # the flight: 14 MB a minute and a query slice past the frame interval
    # after 4 minutes of `nislam run` (docs/fusion.md, "A long flight").
    fastorb = _make_fastorb(intrinsics, cfg, loop_closure=False)
    return [nislam, fastorb]


def _make_fused(intrinsics: CameraIntrinsics, cfg: TrackerSections) -> Tracker:
    from onboard.fusion.fused import FusedTracker

    params = getattr(cfg, "fusion", None) or FusionParams()
    return FusedTracker(fused_parts(intrinsics, cfg), params)


_REGISTRY: dict[str, Callable[[CameraIntrinsics, TrackerSections], Tracker]] = {
    "nislam": _make_nislam,
    "fastorb": _make_fastorb,
    "fused": _make_fused,
}
TRACKER_NAMES: tuple[str, ...] = tuple(_REGISTRY)

# `[tracker] name = "auto"` (the default): each command's own choice. The
# onboard loop (`nislam run`) flies on the fused tracker, which keeps a pose
# while either tracker tracks (docs/fusion.md); `nislam replay` and `bench`
# measure NI-SLAM, the paper's tracker, unless told otherwise.
AUTO = "auto"
SERVICE_TRACKER = "fused"
OFFLINE_TRACKER = "nislam"
# Trackers that report lost without the AHRS ("no attitude"): only they take
# the service's `fallback_tracker`. The fused tracker carries on through an
# attitude gap on FastORB's own rotation (onboard.fusion.fused).
NEEDS_ATTITUDE = frozenset({"nislam"})


def resolve_name(name: str, service: bool) -> str:
    """`name` with "auto" replaced by the onboard loop's (`service`) or the
    offline tools' default."""
    if name != AUTO:
        return name
    return SERVICE_TRACKER if service else OFFLINE_TRACKER


def make_tracker(name: str, intrinsics: CameraIntrinsics, cfg: TrackerSections) -> Tracker:
    """A fresh tracker `name` for a camera with `intrinsics`, parameters from `cfg`."""
    try:
        build = _REGISTRY[name]
    except KeyError:
        raise NislamError(
            f"unknown tracker '{name}' (known: {', '.join(TRACKER_NAMES)})"
        ) from None
    return build(intrinsics, cfg)
