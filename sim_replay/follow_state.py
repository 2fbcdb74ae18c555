"""The simulated vehicle's true state, as a simulator reports it over MAVLink,
placed in a synthetic scene: what `nislam run --sim-follow` renders from.

Messages (read by attribute, so no pymavlink import here):

- SIM_STATE (108, ArduPilot SITL): q1..q4 (w, x, y, z: body FRD to NED),
  xgyro..zgyro (body rates, rad/s), vn, ve, vd (m/s, NED), alt (m), and the
  position as lat/lon. ArduPilot fills the float `lat`/`lon` with degE7
  (not degrees, as common.xml says) and, in newer versions, the int32
  `lat_int`/`lon_int` (degE7) too: those are preferred (1.1 cm steps); a
  float32 degE7 only resolves ~0.3 m, degrees ~2 m.
- HIL_STATE_QUATERNION (115, other simulators): attitude_quaternion (w, x,
  y, z), body rates, lat/lon (degE7), alt (mm), vx, vy, vz (cm/s, NED).

Neither carries the simulator's time: a state holds for the moment it
arrived (host monotonic clock, stamped by the link's reader thread).

Position. Geodetic offsets become metres the way ArduPilot's Location does
it (a sphere, 0.011131884502145034 m per 1e-7 deg of latitude, longitude
scaled by cos(latitude)), so SITL's own NED motion comes back unchanged.
The position steps of lat/lon (1.1 cm at best) would shake the rendered
camera, so a complementary filter follows the reported velocity (exact in a
simulator) and pulls towards the reported position with time constant
`tau_s`: the steps average out, no lag builds up at constant velocity.

Scene. The scene's world W has NED axes (x north, y east, z down). The
vehicle's first state (its anchor) is placed at the scene's start point
`start_W_m`; from then on p_W = start_W_m + (p_NED - p_NED(anchor)), and the
attitude is the reported one (R_W_B = R_NED_B), so the rendered camera and
the simulated AHRS see what the vehicle does, heading included. The anchor
can be kept in a file and reused by the next process (a restarted service
sees the same room where it left it).
"""

from __future__ import annotations

import json
import logging
import math
import os
import threading
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

log = logging.getLogger(__name__)

STATE_TYPES = ("SIM_STATE", "HIL_STATE_QUATERNION")
M_PER_DEG_E7 = 0.011131884502145034  # ArduPilot's LOCATION_SCALING_FACTOR
SNAP_M = 1.0  # a reported position this far from the prediction: jump to it (a sim reset)
ANCHOR_REUSE_M = 50.0  # a kept anchor is reused when the vehicle starts within this of it
HISTORY_S = 2.0  # states kept for poses in the past


@dataclass(frozen=True)
class VehicleState:
    """One reported state; NaN-free (checked by `state_from_message`)."""

    t_ns: int  # host monotonic arrival time: when the state held
    lat_e7: float  # degE7 (float64: keeps sub-unit precision when given)
    lon_e7: float
    alt_m: float
    v_N_m_s: np.ndarray  # (3,) NED
    q_N_B_xyzw: np.ndarray  # (4,) body FRD to NED
    w_B_rad_s: np.ndarray  # (3,) body rates
    fine: bool  # lat/lon resolve ~1 cm (degE7 integers)


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def state_from_message(msg: Any, t_ns: int) -> VehicleState | None:
    """The state a SIM_STATE or HIL_STATE_QUATERNION reports; None for other
    messages or a broken one (NaN, a quaternion far from unit length)."""
    kind = msg.get_type()
    if kind == "SIM_STATE":
        q_wxyz = (msg.q1, msg.q2, msg.q3, msg.q4)
        lat_int, lon_int = getattr(msg, "lat_int", 0), getattr(msg, "lon_int", 0)
        if lat_int or lon_int:
            lat, lon, fine = float(lat_int), float(lon_int), True
        elif abs(msg.lat) > 180.0 or abs(msg.lon) > 360.0:  # ArduPilot: degE7 in a float
            lat, lon, fine = float(msg.lat), float(msg.lon), False
        else:  # degrees, as common.xml says
            lat, lon, fine = float(msg.lat) * 1e7, float(msg.lon) * 1e7, False
        alt = float(msg.alt)
        v = (msg.vn, msg.ve, msg.vd)
        w = (msg.xgyro, msg.ygyro, msg.zgyro)
    elif kind == "HIL_STATE_QUATERNION":
        q_wxyz = tuple(msg.attitude_quaternion)
        lat, lon, fine = float(msg.lat), float(msg.lon), True
        alt = msg.alt * 1e-3
        v = (msg.vx * 0.01, msg.vy * 0.01, msg.vz * 0.01)
        w = (msg.rollspeed, msg.pitchspeed, msg.yawspeed)
    else:
        return None
    if not _finite(*q_wxyz, lat, lon, alt, *v, *w):
        return None
    q = np.array([q_wxyz[1], q_wxyz[2], q_wxyz[3], q_wxyz[0]], dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > 0.01:
        return None
    return VehicleState(t_ns, lat, lon, alt, np.asarray(v, dtype=np.float64), q / norm,
                        np.asarray(w, dtype=np.float64), fine)


@dataclass(frozen=True)
class Anchor:
    """The geodetic point placed at the scene's start point."""

    lat_e7: float
    lon_e7: float
    alt_m: float

    def ned_m(self, s: VehicleState) -> np.ndarray:
        """NED offset [m] of a state from the anchor (ArduPilot's sphere)."""
        lon_scale = math.cos(math.radians(self.lat_e7 * 1e-7))
        return np.array([(s.lat_e7 - self.lat_e7) * M_PER_DEG_E7,
                         (s.lon_e7 - self.lon_e7) * M_PER_DEG_E7 * lon_scale,
                         -(s.alt_m - self.alt_m)])

    def save(self, path: Path) -> None:
        tmp = path.with_name(path.name + ".tmp")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(json.dumps({"lat_e7": self.lat_e7, "lon_e7": self.lon_e7,
                                       "alt_m": self.alt_m}) + "\n")
            os.replace(tmp, path)
        except OSError as e:
            log.warning("cannot keep the sim-follow anchor in %s: %s", path, e.strerror or e)

    @classmethod
    def load(cls, path: Path) -> Anchor | None:
        try:
            d = json.loads(path.read_text())
            return cls(float(d["lat_e7"]), float(d["lon_e7"]), float(d["alt_m"]))
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, TypeError) as e:
            log.warning("ignoring the sim-follow anchor %s: %s", path, e)
            return None


@dataclass(frozen=True)
class BodyPose:
    """The vehicle's body (FRD) in the scene at `t_ns`."""

    t_ns: int
    p_W_m: np.ndarray
    R_W_B: np.ndarray
    v_W_m_s: np.ndarray
    w_B_rad_s: np.ndarray


class VehicleTrack:
    """Reported states in (`push`, from the link's reader thread), the body's
    pose in the scene at any time out (`pose_at`, from the camera and AHRS
    threads): the newest state at or before that time, moved on by its
    velocity and body rates (a state is at most one report period old)."""

    def __init__(self, start_W_m: np.ndarray, tau_s: float = 0.5,
                 anchor_file: Path | None = None, max_age_s: float = 0.5) -> None:
        self.start_W_m = np.asarray(start_W_m, dtype=np.float64)
        self.tau_s = tau_s
        self.anchor_file = anchor_file
        self.max_age_ns = int(max_age_s * 1e9)
        self.anchor: Anchor | None = None
        self.states = 0
        self.rejected = 0
        self.coarse_warned = False
        self._lock = threading.Lock()
        self._poses: deque[BodyPose] = deque()
        self._p_N: np.ndarray | None = None  # filtered NED position
        self._v_N: np.ndarray | None = None
        self._t_ns = 0
        self.first = threading.Event()

    # -- producer (the link's reader thread)
    def push_message(self, msg: Any, t_ns: int) -> None:
        s = state_from_message(msg, t_ns)
        if s is None:
            self.rejected += 1
            return
        self.push(s)

    def push(self, s: VehicleState) -> None:
        if self.anchor is None:
            self.anchor = self._make_anchor(s)
        if not s.fine and not self.coarse_warned:
            self.coarse_warned = True
            log.warning("the simulator reports lat/lon without lat_int/lon_int: positions "
                        "resolve only ~0.3 m; smoothing over %.1f s", 4 * self.tau_s)
        meas = self.anchor.ned_m(s)
        p = self._filter(s, meas)
        pose = BodyPose(s.t_ns, self.start_W_m + p, Rotation.from_quat(s.q_N_B_xyzw).as_matrix(),
                        s.v_N_m_s.copy(), s.w_B_rad_s.copy())
        with self._lock:
            self._poses.append(pose)
            while self._poses and self._poses[0].t_ns < s.t_ns - HISTORY_S * 1e9:
                self._poses.popleft()
            self.states += 1
        self.first.set()

    def _make_anchor(self, s: VehicleState) -> Anchor:
        here = Anchor(s.lat_e7, s.lon_e7, s.alt_m)
        kept = Anchor.load(self.anchor_file) if self.anchor_file is not None else None
        if kept is not None and float(np.linalg.norm(kept.ned_m(s)[:2])) <= ANCHOR_REUSE_M:
            log.info("sim-follow: the vehicle is %.2f m from the kept anchor: the scene stays "
                     "where the last run left it", float(np.linalg.norm(kept.ned_m(s))))
            return kept
        if self.anchor_file is not None:
            here.save(self.anchor_file)
        return here

    def _filter(self, s: VehicleState, meas: np.ndarray) -> np.ndarray:
        """Complementary filter: velocity-propagated, pulled to the report."""
        p, v = self._p_N, self._v_N
        if p is None or v is None:
            out = meas
        else:
            dt = max(0.0, (s.t_ns - self._t_ns) * 1e-9)
            pred = p + 0.5 * (v + s.v_N_m_s) * dt
            tau = self.tau_s * (1.0 if s.fine else 4.0)
            k = min(1.0, dt / tau) if tau > 0 else 1.0
            out = meas if np.linalg.norm(meas - pred) > SNAP_M else pred + k * (meas - pred)
        self._p_N, self._v_N, self._t_ns = out, s.v_N_m_s.copy(), s.t_ns
        return out

    # -- consumers
    def pose_at(self, t_ns: int) -> BodyPose | None:
        """The body at `t_ns`; None before the first state or when the newest
        usable one is older than `max_age_s` (the simulator went quiet)."""
        with self._lock:
            poses = list(self._poses)
        if not poses:
            return None
        ref = poses[-1]
        for pose in reversed(poses):
            ref = pose
            if pose.t_ns <= t_ns:
                break
        dt = (t_ns - ref.t_ns) * 1e-9
        if dt * 1e9 > self.max_age_ns:
            return None
        R = ref.R_W_B @ Rotation.from_rotvec(ref.w_B_rad_s * dt).as_matrix()
        return BodyPose(t_ns, ref.p_W_m + ref.v_W_m_s * dt, R, ref.v_W_m_s, ref.w_B_rad_s)
