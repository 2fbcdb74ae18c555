"""Where results go: the MAVLink vision-position feed to the flight
controller, zenoh pose/status/map publishing and its listener, the key-frame
map codec, PLY maps and trajectory plots. Each output runs its own threads
behind a bounded queue, so the tracking loop never waits on a link.
"""
