"""pymavlink, loaded with the MAVLink 2 messages.

pymavlink picks MAVLink 1 or 2 when it is first imported, from the
environment variable MAVLINK20; with MAVLink 1 ODOMETRY does not exist.
Importing this module imports nothing of pymavlink; `load_mavutil()` does,
setting MAVLINK20=1 first.
"""

from __future__ import annotations

import os
from typing import Any

from onboard import NislamError


def load_mavutil() -> Any:
    """pymavlink's mavutil with the MAVLink 2 messages.

    mavutil loads the MAVLink 2 dialect when MAVLINK20 is set (to anything)
    at its first import, so the variable is set here, right before that
    import. Something that imported pymavlink earlier without it got
    MAVLink 1, which is refused here rather than failing at the first send.
    """
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    if mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":
        raise NislamError("pymavlink was loaded with MAVLink 1 (MAVLINK20 unset or 0 at its "
                          "first import); ODOMETRY needs MAVLink 2")
    return mavutil
