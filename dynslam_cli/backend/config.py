"""Configuration of the keyframe bundle-adjustment backend (``dynslam_cli.backend``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from dynslam_cli.config.fields import opt


@dataclass
class BackendConfig:
    features: int = opt(1000, "ORB keypoints per frame (spread over an image grid; ORB-SLAM2 uses 1000 at 640x480).",
                        min=50)
    window: int = opt(10, "Keyframes optimised by local bundle adjustment: the newest keyframe and its most "
                      "covisible ones (the local map frames are tracked against is twice as many).", min=2)
    huber_px: float = opt(2.8, "Robust (Huber) kernel width in pixels at the finest ORB scale, for the pose and the "
                          "bundle adjustment; observations beyond it on the chi-square scale (2.8 px ~ the 95 % "
                          "gate 7.815 of a 3-D RGB-D residual) are outliers.", above=0)
    min_matches: int = opt(20, "Fewer static inlier matches than this after the motion-model search, the wider "
                           "search and PnP relocalisation: the frame is 'lost' (constant-velocity pose).", min=6)
    keyframe_ratio: float = opt(0.75, "A new keyframe when the frame tracks fewer than this fraction of the "
                                "reference keyframe's landmarks (ORB-SLAM2 RGB-D: 0.75).", above=0, max=1)

    # Constants (not keys).  Radius (px at 640 px width, times the keypoint's scale) in which a local-map landmark
    # projected with the constant-velocity pose looks for its keypoint; the second pass, from the optimised pose,
    # uses a quarter of it.
    SEARCH_PX: ClassVar[float] = 15.0
    # A new keyframe at the latest this many frames after the last one.
    KEYFRAME_MAX_GAP: ClassVar[int] = 30
    # Virtual stereo baseline (m) of gtsam's RGB-D stereo factor (u_R = u - fx*b/depth).  Only a parametrisation: the
    # depth's noise is Sequence.depth_noise, carried to the disparity, independent of the pixel's (backend/tracking.information).
    BASELINE: ClassVar[float] = 0.08
