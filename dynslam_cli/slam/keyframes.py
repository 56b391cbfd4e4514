"""Keyframe ray store: each keyframe keeps a random subset of its pixels as rays for replay.

Per stored ray: pixel (u, v), colour, depth, instance id (int32, -1 = none) and a mutable
``usable`` flag (False = the dynamic module excluded the ray; bundle adjustment skips it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Keyframe:
    frame_id: int            # index of the frame in the SLAM's own stream (0, 5, 10, ...)
    timestamp: float
    pixels: np.ndarray       # (M, 2) int32 (u, v)
    rgb: np.ndarray          # (M, 3) uint8
    depth: np.ndarray        # (M,) float32 metres (> 0)
    instance_ids: np.ndarray  # (M,) int32, -1 = none
    usable: np.ndarray       # (M,) bool, mutable
    pose_c2w: np.ndarray = field(default_factory=lambda: np.eye(4))  # refined by BA

    def __len__(self) -> int:
        return len(self.depth)

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("frame_id", "timestamp", "pixels", "rgb", "depth",
                                              "instance_ids", "usable", "pose_c2w")}

    @staticmethod
    def from_dict(d: dict) -> "Keyframe":
        return Keyframe(int(d["frame_id"]), float(d["timestamp"]), np.asarray(d["pixels"]), np.asarray(d["rgb"]),
                        np.asarray(d["depth"]), np.asarray(d["instance_ids"]), np.array(d["usable"], bool),
                        np.array(d["pose_c2w"], np.float64))


def valid_pixels(depth: np.ndarray, mask: np.ndarray | None, border: int, need_depth: bool = True) -> np.ndarray:
    """Flat indices of pixels that may be sampled: inside the border, mask True, depth > 0."""
    h, w = depth.shape
    ok = np.zeros((h, w), bool)
    b = max(0, int(border))
    if h > 2 * b and w > 2 * b:
        ok[b:h - b, b:w - b] = True
    if need_depth:
        ok &= depth > 0
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != (h, w):
            from dynslam_cli.errors import DynslamError
            raise DynslamError(f"mask shape {m.shape} does not match the frame {h}x{w}")
        ok &= m.astype(bool)
    return np.flatnonzero(ok)
