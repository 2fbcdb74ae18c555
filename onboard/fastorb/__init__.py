"""The FastORB tracker (Fu et al., "Fast ORB-SLAM without Keypoint
Descriptors", IEEE TIP 2022): RGB-D only, ORB keypoints followed by
motion-model-seeded pyramid optical flow, descriptors only for key frames.
Pure: arrays and messages in, a `TrackResult` out (`FastOrbTracker.track`).
"""
