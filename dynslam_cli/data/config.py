"""Configuration of sequence reading."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from dynslam_cli.config.fields import numbers, opt


@dataclass
class DataConfig:
    root: str = opt("", "Data root where named sequences live; empty = $DYNSLAM_DATA or ./data.")
    depth_scale: float = opt(
        5000.0, "Divide the uint16 depth PNG by this to get metres (TUM, Bonn); synthetic folders use their synth.json value.",
        above=0)
    max_time_diff: float = opt(0.02, "Maximum rgb/depth/ground-truth timestamp difference (s) when associating.", above=0)
    max_depth: float = opt(0.0, "Depth beyond this (m) is treated as invalid; 0 keeps all.", min=0)
    intrinsics: list | None = opt(None, "fx, fy, cx, cy in pixels; null = the dataset's own.")
    distortion: list | None = opt(None, "k1, k2, p1, p2[, k3] (OpenCV order); null = the dataset's own.")
    start: int = opt(0, "First frame index (after association).", min=0)
    frames: int = opt(0, "Number of frames to use; 0 = all.", min=0)
    stride: int = opt(1, "Use every S-th frame.", min=1)

    # The depth's standard deviation at keypoints per metre^2 of depth (sigma = DEPTH_NOISE x depth^2, m: structured
    # light), which the keyframe backend weighs depth against pixel positions by, for real sensors: their random and
    # systematic error together, about ORB-SLAM2's RGB-D depth weight (docs/experiments.md).  A synthetic folder's
    # synth.json gives its renderer's own (Sequence.depth_noise).  Not a key: no measured reason to change it yet.
    DEPTH_NOISE: ClassVar[float] = 0.03

    def validate(self, key):
        """Cross-field and list rules (see config.fields)."""
        if self.intrinsics is not None:
            vals = numbers(self.intrinsics, 4)
            if vals is None or vals[0] <= 0 or vals[1] <= 0:
                yield f"{key('intrinsics')} must be null or 4 numbers fx, fy, cx, cy with fx, fy > 0 (got {self.intrinsics!r})"
        if self.distortion is not None:
            vals = numbers(self.distortion)
            if vals is None or len(vals) not in (4, 5, 8, 12, 14):
                yield (f"{key('distortion')} must be null or 4, 5, 8, 12 or 14 numbers k1, k2, p1, p2[, k3, ...] "
                       f"(got {self.distortion!r})")
