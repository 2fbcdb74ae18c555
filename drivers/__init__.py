"""Hardware-facing driver threads (AHRS, OAK-D camera, flight-controller link)."""

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())
