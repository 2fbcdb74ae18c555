"""nislam-onboard: indoor positioning from RGB-D + attitude (NI-SLAM) for small drones."""

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())

__version__ = "0.1.0"


class NislamError(Exception):
    """Base of every error this project raises on bad input or configuration.

    Entry points turn it into one log line and exit code 1.
    """
