"""dynslam: dense neural RGB-D SLAM for dynamic scenes (continual-learning motion classifier)."""

from dynslam_cli.utils.threads import passive_openmp

passive_openmp()  # before anything imports torch: libgomp reads its wait policy once (utils/threads.py)

__version__ = "0.1.0"
