"""dynslam: dense neural RGB-D SLAM for dynamic scenes (continual-learning motion classifier)."""

__version__ = "0.1.0"
