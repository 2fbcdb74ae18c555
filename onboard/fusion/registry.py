"""The tracker interface and the factory that builds one from config.

Every tracker is a pure core (arrays in, a result out) behind the same
`Tracker` protocol, so replay, bench and the onboard loop never ask which one
they hold.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

from onboard import NislamError
from onboard.frames import AttitudeSource, CameraIntrinsics, RgbdFrame
from onboard.frames import KeyframeCloud, TrackResult
from onboard.fastorb import FastOrbTracker
from onboard.nislam import NislamTracker

if TYPE_CHECKING:  # config imports TRACKER_NAMES from here
    from onboard.config import Config


class Tracker(Protocol):
    """One camera's tracking front end."""

    name: str

    def track(self, frame: RgbdFrame, attitude: AttitudeSource) -> TrackResult:
        """Track one frame; attitude is looked up at the frame's capture time."""
        ...

    def finish(self) -> KeyframeCloud | None:
        """End of a run: the current key's cloud for the map, if any."""
        ...


def _make_nislam(intrinsics: CameraIntrinsics, cfg: Config) -> Tracker:
    return NislamTracker(intrinsics, cfg.nislam)


def _make_fastorb(intrinsics: CameraIntrinsics, cfg: Config) -> Tracker:
    return FastOrbTracker(intrinsics, cfg.fastorb)


_REGISTRY: dict[str, Callable[[CameraIntrinsics, Config], Tracker]] = {
    "nislam": _make_nislam,
    "fastorb": _make_fastorb,
}
TRACKER_NAMES: tuple[str, ...] = tuple(_REGISTRY)


def make_tracker(name: str, intrinsics: CameraIntrinsics, cfg: Config) -> Tracker:
    """A fresh tracker `name` for a camera with `intrinsics`, parameters from `cfg`."""
    try:
        build = _REGISTRY[name]
    except KeyError:
        raise NislamError(
            f"unknown tracker '{name}' (known: {', '.join(TRACKER_NAMES)})"
        ) from None
    return build(intrinsics, cfg)
