"""Configuration of sequence reading."""

from __future__ import annotations

from dataclasses import dataclass

from dynslam_cli.config.fields import opt


@dataclass
class DataConfig:
    root: str = opt("", "Data root where named sequences live; empty = $DYNSLAM_DATA or ./data.")
    depth_scale: float = opt(
        5000.0, "Divide the uint16 depth PNG by this to get metres (TUM, Bonn); synthetic folders use their synth.json value.")
    max_time_diff: float = opt(0.02, "Maximum rgb/depth/ground-truth timestamp difference (s) when associating.")
    gt_interpolate: bool = opt(
        True, "Interpolate ground truth at rgb timestamps between samples <= 2*max_time_diff apart; "
        "false = nearest sample within max_time_diff.")
    max_depth: float = opt(0.0, "Depth beyond this (m) is treated as invalid; 0 keeps all.")
    intrinsics: list | None = opt(None, "fx, fy, cx, cy in pixels; null = the dataset's own.")
    distortion: list | None = opt(None, "k1, k2, p1, p2[, k3] (OpenCV order); null = the dataset's own.")
    undistort: bool = opt(True, "Undistort rgb and depth when the distortion is non-zero.")
    start: int = opt(0, "First frame index (after association).")
    frames: int = opt(0, "Number of frames to use; 0 = all.")
    stride: int = opt(1, "Use every S-th frame.")
