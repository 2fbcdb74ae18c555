"""Where several trackers and the AHRS become one pose stream: the tracker
registry (the one list of tracker names) and the fallback switch that runs
FastORB while the attitude is missing. Pure, like the trackers it combines.
"""
