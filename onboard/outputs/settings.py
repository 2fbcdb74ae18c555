"""The outputs' configuration sections: `[mavlink]` (the vision-position feed),
`[zenoh]` (pose, status and map publishing, `nislam listen`, `nislam ground`)
and `[router]` (`nislam router`, the fleet's zenoh router).
"""

from __future__ import annotations

from dataclasses import dataclass

MOUNT_NAMES = ("forward", "down", "custom")


WORLD_FRAMES = ("frd", "flu")


MAVLINK_MESSAGES = ("odometry", "vision_position")


ZENOH_MODES = ("peer", "client", "router")


# zenoh.Priority names, highest first (zenoh's eight transmission queues).
ZENOH_PRIORITIES = ("real_time", "interactive_high", "interactive_low", "data_high", "data",
                    "data_low", "background")


@dataclass(frozen=True)
class MavlinkConfig:
    """The vision-position feed to the flight controller (onboard/outputs/mavlink.py)."""

    enabled: bool = False
    connect: str = "udpout:127.0.0.1:14550"  # pymavlink connection string
    baud: int = 921600  # serial baud rate unless `connect` names one ("/dev/ttyAMA0,921600")
    system_id: int = 1  # our MAVLink system id: the vehicle's (the autopilot's) id
    component_id: int = 197  # MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY
    message: str = "odometry"  # or "vision_position" (VISION_POSITION/SPEED_ESTIMATE)
    mount: str = "forward"  # camera mount R_B_C: "forward", "down" or "custom"
    mount_q_B_C_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)  # "custom"
    world_frame: str = "frd"  # axes of the tracker world W: "frd" (z down) or "flu" (z up)
    degraded_quality: int = 20  # tracking below this quality is "degraded" (CRITICAL)
    jump_m: float = 0.1  # a step longer than this ...
    jump_speed_m_s: float = 10.0  # ... and faster than this is a jump: reset_counter + 1
    velocity_window_s: float = 0.1  # velocity from poses up to this far apart
    heartbeat_period_s: float = 1.0
    stale_s: float = 0.5  # no tracker result for this long = lost ("no frames")
    reconnect_s: float = 1.0  # retry a link that failed after this long
    queue_frames: int = 8  # results waiting for the sender; the oldest is dropped
    set_origin: bool = False  # send SET_GPS_GLOBAL_ORIGIN at start (the GPS-less EKF origin)
    set_home: bool = False  # with set_origin, SET_HOME_POSITION too (ArduPilot ignores it)
    origin_lat_deg: float = 0.0
    origin_lon_deg: float = 0.0
    origin_alt_m: float = 0.0  # above mean sea level
    # Where the last reset_counter sent is kept, so a restarted service never
    # reuses it: "" = $STATE_DIRECTORY (systemd), else $XDG_STATE_HOME/nislam,
    # else ~/.local/state/nislam (onboard/outputs/mavlink_origin.py).
    state_dir: str = ""
    signing_key_file: str = ""  # MAVLink 2 signing: 32-byte key file (64 hex digits or a
    # passphrase, SHA-256 as MAVProxy); readable by the service user only. "" = no signing
    signing_link_id: int = 0  # our link id in the signature (0-255)


@dataclass(frozen=True)
class ZenohConfig:
    """Pose, status and map publishing (onboard/outputs/zenoh_out.py) and `nislam listen`."""

    enabled: bool = False
    vehicle: str = "drone1"  # keys live under nislam/<vehicle>/
    mode: str = "peer"  # zenoh session mode: "peer", "client" or "router"
    connect: tuple[str, ...] = ()  # endpoints to connect to, e.g. "tcp/192.168.1.10:7447"
    listen: tuple[str, ...] = ()  # endpoints to listen on, e.g. "tcp/0.0.0.0:7447"
    multicast_scouting: bool = False  # find peers by UDP multicast (off: explicit endpoints)
    status_period_s: float = 1.0
    queue_frames: int = 32  # poses waiting for the publisher; the oldest is dropped
    map_max_mb: float = 512.0  # key frames kept for late joiners; the oldest go first
    map_rate_kb_s: float = 0.0  # key-frame puts at most this many kB/s on average; 0 = no limit
    pose_priority: str = "interactive_high"  # zenoh priority of pose (a ZENOH_PRIORITIES name)
    status_priority: str = "data_high"
    map_priority: str = "data_low"  # key frames and map replies: below poses on a busy link
    tls_root_ca: str = ""  # fleet CA certificate (PEM); set = TLS (tls/... endpoints) with the two below
    tls_certificate: str = ""  # this node's certificate from the fleet CA (PEM) ...
    tls_private_key: str = ""  # ... and its key: mutual TLS (the router checks it)


@dataclass(frozen=True)
class RouterConfig:
    """`nislam router`: a zenoh router for the fleet (onboard/outputs/router.py)."""

    listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)  # endpoints vehicles and grounds reach
    connect: tuple[str, ...] = ()  # other routers (several rooms / Wi-Fi cells)
    tls_root_ca: str = ""  # fleet CA: with the two below, listen on tls/... with mutual TLS
    tls_certificate: str = ""
    tls_private_key: str = ""
    acl: bool = False  # access control by certificate common name (needs TLS)
    vehicles: tuple[str, ...] = ()  # vehicle ids = their certificates' common names
    grounds: tuple[str, ...] = ("ground",)  # ground stations' certificate common names
