"""The NI-SLAM tracker (Wang, Yuan, Xie, "Non-Iterative SLAM", ICAR 2017):
attitude from the AHRS, translation from a kernel correlation filter on
axonometric projections of the depth cloud. Pure: arrays and messages in, a
`TrackResult` out (`NislamTracker.track`).
"""
