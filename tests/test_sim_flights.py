"""Synthetic flights: limits a small indoor drone respects, smoothness, clearance
and the attitude a multirotor must have to fly them."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from onboard import NislamError
from sim_replay.flights import (
    GRAVITY_W,
    SCENARIOS,
    Flight,
    attitude_from_acceleration,
    ramp,
    scenario,
)
from sim_replay.scene import make_scene

T_S = np.arange(-0.5, 60.0, 0.005)


def _kinematics(name: str):
    flight = Flight(scenario(name))
    p, r = flight.body_pose(T_S)
    speed = np.linalg.norm(flight.velocity(T_S), axis=1)
    rel = Rotation.from_matrix(r[:-1]).inv() * Rotation.from_matrix(r[1:])
    rate_deg_s = np.degrees(np.linalg.norm(rel.as_rotvec(), axis=1)) / np.diff(T_S)
    return flight, p, r, speed, rate_deg_s


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_flight_stays_within_drone_limits_and_clear_of_the_scene(name):
    flight, p, r, speed, rate = _kinematics(name)
    assert speed.max() < 1.55, speed.max()
    assert rate.max() < 100.0, rate.max()
    clearance = make_scene(flight.scenario.scene).clearance_m(p)
    assert clearance.min() > 0.5, clearance.min()
    # Starts from rest: hover before take-off.
    assert speed[T_S < 0].max() < 0.2
    # Rotation matrices proper and orthonormal.
    assert np.allclose(r @ np.swapaxes(r, 1, 2), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(r), 1.0)


def test_the_fast_scenarios_reach_the_limits():
    *_, speed, rate = _kinematics("aggressive")
    assert speed.max() > 1.4 and rate.max() > 80.0
    *_, _, rate = _kinematics("yaw-spin")
    assert 88.0 < rate[T_S[1:] > 5].max() < 92.0


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_trajectories_are_smooth(name):
    """Position, velocity, acceleration (and so attitude) continuous: bounded
    jerk and bounded angular acceleration across take-off and everywhere."""
    flight, _p, _r, _speed, rate = _kinematics(name)
    acc = flight.acceleration(T_S)
    jerk = np.linalg.norm(np.diff(acc, axis=0), axis=1) / np.diff(T_S)
    assert jerk.max() < 15.0, jerk.max()  # m/s^3: no steps in acceleration
    ang_acc = np.abs(np.diff(rate)) / np.diff(T_S)[1:]
    assert ang_acc.max() < 600.0, ang_acc.max()  # deg/s^2: no steps in body rate


def test_ramp_is_c3_from_rest():
    t = np.array([-1.0, 0.0, 1.0, 2.0, 3.0])
    s = ramp(t, ramp_s=2.0)
    assert s[0] == 0.0 and s[1] == 0.0 and np.isclose(s[3], 1.0) and np.isclose(s[4], 2.0)
    h = 1e-4
    ds = (ramp(t + h, 2.0) - ramp(t - h, 2.0)) / (2 * h)
    assert np.allclose(ds, [0.0, 0.0, 0.5, 1.0, 1.0], atol=1e-6)


def test_multirotor_attitude_follows_thrust_and_heading():
    # Hover: level, nose on the heading.
    r = attitude_from_acceleration(np.zeros((1, 3)), np.array([0.5]))[0]
    assert np.allclose(r, Rotation.from_euler("z", 0.5).as_matrix(), atol=1e-12)
    # Accelerating north (x) at 2 m/s^2: the nose dips (body x points below
    # the horizon, z down) and thrust (-z_B) leans into the acceleration.
    acc = np.array([[2.0, 0.0, 0.0]])
    r = attitude_from_acceleration(acc, np.array([0.0]))[0]
    assert r[2, 0] > 0.1
    thrust = -r[:, 2]
    expected = (acc[0] - GRAVITY_W) / np.linalg.norm(acc[0] - GRAVITY_W)
    assert np.allclose(thrust, expected, atol=1e-12)
    assert np.isclose(np.degrees(np.arccos(r[2, 2])), np.degrees(np.arctan2(2.0, 9.80665)))


def test_unknown_scenario_is_a_clear_error():
    with pytest.raises(NislamError, match="unknown scenario 'loop'.*circle"):
        scenario("loop")
