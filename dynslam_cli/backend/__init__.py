"""Keyframe bundle-adjustment backend (ORB-SLAM2 RGB-D style): landmarks on static pixels, frame
tracking against a covisible local map, local bundle adjustment (gtsam) and keyframe selection by
overlap.  :class:`~dynslam_cli.backend.backend.Backend` composes them."""
