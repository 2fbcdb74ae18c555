"""Recorded and synthetic sequences: TUM-layout readers, replay sources, sensor error models."""

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())
