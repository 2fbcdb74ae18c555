"""Where several trackers and the AHRS become one pose stream: the tracker
registry (the one list of tracker names), the fallback switch that runs
FastORB while the attitude is missing, and the fused tracker (`fused.py`,
`filter.py`, `measurements.py`) that runs both and fuses their motions with
the AHRS attitude. Pure, like the trackers it combines.
"""
