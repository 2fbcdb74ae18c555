"""The pure shared core: frame and result messages, the camera model,
rotations and rigid transforms, the attitude buffer, the source-thread base
every camera and AHRS source is built on, trajectories and their evaluation
(ATE, RPE). Everything above imports it; it imports nothing above it.
"""
