"""A frame matched against a NI-SLAM key (its pose, Eq. 15 and 18), and the
last trusted frame a new key is made from."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from onboard.nislam.correlation import Peak
from onboard.nislam.depth import DepthFit
from onboard.nislam.keys import Key
from onboard.nislam.projection import Cloud
from onboard.nislam.results import pose_variance


@dataclass(frozen=True)
class Match:
    """A frame matched against the key: pose and what the result reports."""

    p_W_m: np.ndarray
    peak: Peak
    depth: DepthFit
    theta_rad: np.ndarray  # residual rotation seen by the colour layers (0 if not measured)
    pose_var: np.ndarray  # (6,) in the world frame


@dataclass
class Prev:
    """The last trusted frame, kept to seed a new key: its position as an
    offset from the key it was matched against (`base`, None after a
    restart: then the offset is the position), so a refined key position
    carries over."""

    t_s: float
    cloud: Cloud
    R_W_C: np.ndarray
    base: Key | None
    d_W_m: np.ndarray
    var_W_m2: np.ndarray  # (3,) of the offset
    # The geometry's rotation from the attitude at t_s (its depth captured at
    # another instant: tracker._track); None: the same instant.
    r_geom: np.ndarray | None = None
    # The same frame's cloud at another pixel step (a new key may want one).
    remake: Callable[[int], Cloud] | None = None

    @property
    def p_W_m(self) -> np.ndarray:
        return self.d_W_m if self.base is None else self.base.p_W_m + self.d_W_m


def pose_from_match(key: Key, peak: Peak, depth: DepthFit, theta_img: np.ndarray) -> Match:
    """The frame's position from its shift against `key` and its depth
    translation; content moves opposite to the camera (ref. §9): t = -d s."""
    s = key.img.res_m
    t_inc = np.array([-peak.du_cells * s, -peak.dv_cells * s, depth.tz_m])
    p_W = key.p_W_m + key.R_W_C @ t_inc
    pose_var = pose_variance(peak, s, depth.var_z_m2, key.R_W_C)
    return Match(p_W, peak, depth, theta_img, pose_var)
