"""Tracking, keyframes, bundle adjustment and the ``SLAM`` system."""
