"""Named flights a small multirotor flies indoors, with their exact poses.

Each scenario gives a smooth position p_W(t) and heading psi(t) (closed-form,
infinitely differentiable after a C3 take-off ramp); the body attitude
follows from the dynamics like a real quadrotor's (differential flatness):
the thrust axis -z_B points along the specific force a - g, the nose turns to
psi. Accelerating therefore tilts the drone, as it must.

World W: z down (docs/design.md); t_s is the time since the flight started
(negative times hover at the start pose).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from onboard import NislamError

GRAVITY_W = np.array([0.0, 0.0, 9.80665])  # z down
RAMP_S = 2.0  # the take-off ramp: speed grows from 0 over this time
_FD_STEP_S = 1e-3  # finite-difference step for the acceleration (error ~1e-7 m/s^2)

PathFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]  # t -> (p (N,3), psi (N,))


def ramp(t_s: np.ndarray, ramp_s: float = RAMP_S) -> np.ndarray:
    """Progress s(t): 0 before the start, ds/dt rising from 0 to 1 over
    `ramp_s` along a C3 smoothstep (-20x^7 + 70x^6 - 84x^5 + 35x^4), then
    s = t - ramp_s / 2. Position p(s(t)) then has continuous jerk at take-off."""
    t = np.asarray(t_s, dtype=np.float64)
    x = np.clip(t / ramp_s, 0.0, 1.0)
    # Integral of the smoothstep from 0 to x.
    inner = ramp_s * x**5 * (-2.5 * x**3 + 10.0 * x**2 - 14.0 * x + 7.0)
    return np.where(t >= ramp_s, t - ramp_s / 2.0, inner)


@dataclass(frozen=True)
class Scenario:
    name: str
    scene: str
    description: str
    path: PathFn


def _hover(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Holding position near the west wall, facing the room: a few cm of drift."""
    p = np.stack([
        -2.4 + 0.03 * np.sin(2 * np.pi * 0.23 * t) + 0.015 * np.sin(2 * np.pi * 0.61 * t + 0.5),
        1.6 + 0.025 * np.sin(2 * np.pi * 0.31 * t + 1.0),
        -1.2 + 0.02 * np.sin(2 * np.pi * 0.17 * t + 2.0),
    ], axis=1)
    psi = -0.35 + 0.05 * np.sin(2 * np.pi * 0.11 * t)
    return p, psi


_ORBIT_CENTRE = np.array([0.0, 1.0])  # the column
_ORBIT_R_M = 1.4
_ORBIT_RATE = 0.45  # rad/s: 0.63 m/s, 26 deg/s


def _circle(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An orbit around the column, nose on it: 1.4 m radius, 0.63 m/s."""
    th = -np.pi / 2 + _ORBIT_RATE * ramp(t)
    p = np.stack([
        _ORBIT_CENTRE[0] + _ORBIT_R_M * np.cos(th),
        _ORBIT_CENTRE[1] + _ORBIT_R_M * np.sin(th),
        np.full_like(th, -1.3),
    ], axis=1)
    return p, th + np.pi


def _lemniscate(t: np.ndarray, centre: tuple[float, float], a: float, b: float,
                rate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gerono figure eight (x = a sin th, y = b sin th cos th) and its heading."""
    th = rate * ramp(t)
    x = centre[0] + a * np.sin(th)
    y = centre[1] + b * np.sin(th) * np.cos(th)
    # Heading along the path from the closed-form tangent (rate > 0).
    psi = np.arctan2(b * np.cos(2 * th), a * np.cos(th))
    return x, y, psi


def _figure8(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A figure eight in the south half of the room, nose along the path, 0.8 m/s peak."""
    x, y, psi = _lemniscate(t, (0.0, -1.7), 2.2, 1.4, 2 * np.pi / 20.0)
    return np.stack([x, y, np.full_like(x, -1.3)], axis=1), psi


def _aggressive(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A fast figure eight (1.5 m/s) with sideways jinks, climbs and yaw swings
    up to ~90 deg/s: the tracker's stress test."""
    x, y, psi = _lemniscate(t, (0.0, -1.2), 2.6, 1.8, 0.45)
    s = ramp(t)
    jink = 0.08 * np.sin(2 * np.pi * 0.7 * s)
    # Sideways to the path: the jink is a lateral acceleration (tilt), not speed.
    x = x - jink * np.sin(psi)
    y = y + jink * np.cos(psi)
    z = -1.3 + 0.2 * np.sin(2 * np.pi * 0.25 * s)
    psi = psi + 0.25 * np.sin(2 * np.pi * 0.25 * s)
    return np.stack([x, y, z], axis=1), psi


def _corridor(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Up and down a corridor (10 m legs, 1.1 m/s peak), turning round at each end."""
    phase = 2 * np.pi / 28.0 * ramp(t)
    x = -5.0 * np.cos(phase)
    y = 0.15 * np.sin(2 * np.pi * 0.09 * ramp(t))
    z = -1.3 + 0.05 * np.sin(2 * np.pi * 0.13 * ramp(t))
    # Nose along +x on the way out (sin > 0), along -x on the way back; the
    # turn happens where the drone slows to a stop (tanh switch, ~60 deg/s).
    k = 3.0
    psi = 0.5 * np.pi * (1.0 - np.tanh(k * np.sin(phase)) / math.tanh(k))
    return np.stack([x, y, z], axis=1), psi


def _yaw_spin(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hover turning on the spot, the rate rising to 90 deg/s."""
    p = np.stack([
        2.0 + 0.02 * np.sin(2 * np.pi * 0.2 * t),
        -1.0 + 0.02 * np.sin(2 * np.pi * 0.27 * t + 1.0),
        -1.3 + 0.015 * np.sin(2 * np.pi * 0.15 * t),
    ], axis=1)
    return p, 0.3 + np.radians(90.0) * ramp(t, ramp_s=4.0)


def _blank_turn(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Turning at 30 deg/s in the middle of the half-painted room, swaying
    0.3 m: each turn has a stretch of about 4 s facing the plain east half."""
    s = ramp(t)
    p = np.stack([
        -0.5 + 0.3 * np.sin(2 * np.pi * 0.1 * s),
        0.2 * np.sin(2 * np.pi * 0.07 * s + 0.5),
        -1.3 + 0.1 * np.sin(2 * np.pi * 0.13 * s),
    ], axis=1)
    return p, np.pi + np.radians(30.0) * s


SCENARIOS: dict[str, Scenario] = {
    s.name: s for s in (
        Scenario("hover", "room", "holding position, a few cm of drift", _hover),
        Scenario("circle", "room", "orbit of a column, 1.4 m radius, 0.63 m/s, 26 deg/s",
                 _circle),
        Scenario("figure8", "room", "figure eight, nose along the path, 0.8 m/s", _figure8),
        Scenario("corridor", "corridor", "up and down a 14 m corridor, 1.1 m/s, turns at "
                 "the ends", _corridor),
        Scenario("yaw-spin", "room", "turning on the spot up to 90 deg/s", _yaw_spin),
        Scenario("blank-turn", "half-painted", "turning at 30 deg/s in a room whose east "
                 "half is plain paint (a textureless stretch each turn)", _blank_turn),
        Scenario("aggressive", "room", "fast figure eight, 1.5 m/s, jinks, climbs, yaw "
                 "swings to 90 deg/s", _aggressive),
    )
}


def scenario(name: str) -> Scenario:
    try:
        return SCENARIOS[name]
    except KeyError:
        raise NislamError(
            f"unknown scenario {name!r} (known: {', '.join(SCENARIOS)})"
        ) from None


class Flight:
    """Exact body poses of a scenario at any time."""

    def __init__(self, scen: Scenario) -> None:
        self.scenario = scen

    def position(self, t_s) -> np.ndarray:
        return self.scenario.path(np.atleast_1d(np.asarray(t_s, dtype=np.float64)))[0]

    def velocity(self, t_s) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        h = _FD_STEP_S
        return (self.position(t + h) - self.position(t - h)) / (2 * h)

    def acceleration(self, t_s) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        h = _FD_STEP_S
        return (self.position(t + h) - 2 * self.position(t) + self.position(t - h)) / (h * h)

    def body_pose(self, t_s) -> tuple[np.ndarray, np.ndarray]:
        """(p_W_m (N, 3), R_W_B (N, 3, 3)) of the body (FRD) at `t_s`."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        p, psi = self.scenario.path(t)
        return p, attitude_from_acceleration(self.acceleration(t), psi)

    def R_W_B(self, t_s) -> np.ndarray:
        return self.body_pose(t_s)[1]


def attitude_from_acceleration(acc_W: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """R_W_B (N, 3, 3) of a multirotor: body z opposite the specific force
    (thrust pulls along -z_B), nose as close to heading `psi` as the tilt allows."""
    f = acc_W - GRAVITY_W  # specific force; (0, 0, -g) in hover
    z_b = -f / np.linalg.norm(f, axis=1, keepdims=True)
    heading = np.stack([np.cos(psi), np.sin(psi), np.zeros_like(psi)], axis=1)
    y_b = np.cross(z_b, heading)
    y_b /= np.linalg.norm(y_b, axis=1, keepdims=True)
    x_b = np.cross(y_b, z_b)
    return np.stack([x_b, y_b, z_b], axis=2)  # columns: body axes in W
