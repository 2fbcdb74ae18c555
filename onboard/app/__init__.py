"""The application: the `nislam` command line, typed configuration, the
onboard service loop and its health, replay and bench, recording, the
hardware wiring and systemd notification. The only layer that configures
logging and reads the configuration as a whole.
"""
