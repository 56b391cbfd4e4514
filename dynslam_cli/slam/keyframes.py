"""Keyframe ray store: each keyframe keeps a random subset of its pixels as rays for replay.

Per stored ray: pixel (u, v), colour, depth, instance id (int32, -1 = none) and a mutable
``usable`` flag (False = the dynamic module excluded the ray; bundle adjustment skips it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dynslam_cli.geometry.camera import pixel_dirs, transform


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
    # the keyframe's depth map on its static pixels (0 elsewhere) every DEPTH_STRIDE pixels (float16;
    # None = not kept): what the map was taught from it, for motion.checkable.keyframe_visibility
    depth_small: np.ndarray | None = None
    # (M, 2) int32: the largest and smallest instance id within the dynamic mask's dilation radius
    # of each ray (None = not kept); a ray is unusable when any of its ids is dynamic
    near_ids: np.ndarray | None = None
    # the keyframe's whole depth map (movers included) every DEPTH_STRIDE pixels (float16; None = not
    # kept): what the camera saw, for motion.stayed.stationary_instances and motion.forget.forget_overtaken
    depth_raw_small: np.ndarray | None = None
    # (M,) bool: rays whose surface point a later frame saw gone (a departed object; motion.forget); never usable
    gone: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.depth)

    def world_points(self, intr) -> np.ndarray:
        """(M, 3) world points of the stored rays (pixels back-projected at their depth, posed)."""
        dirs = pixel_dirs(self.pixels[:, 0], self.pixels[:, 1], intr.fx, intr.fy, intr.cx, intr.cy)
        return transform(self.pose_c2w, dirs * self.depth[:, None])

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("frame_id", "timestamp", "pixels", "rgb", "depth",
                                              "instance_ids", "usable", "pose_c2w", "depth_small", "near_ids",
                                              "depth_raw_small", "gone")}

    @staticmethod
    def from_dict(d: dict) -> "Keyframe":
        def opt_array(key):
            v = d.get(key)
            return None if v is None else np.asarray(v)

        return Keyframe(int(d["frame_id"]), float(d["timestamp"]), np.asarray(d["pixels"]), np.asarray(d["rgb"]),
                        np.asarray(d["depth"]), np.asarray(d["instance_ids"]), np.array(d["usable"], bool),
                        np.array(d["pose_c2w"], np.float64), opt_array("depth_small"), opt_array("near_ids"),
                        opt_array("depth_raw_small"), opt_array("gone"))


DEPTH_STRIDE = 4


def subsample_depth(depth: np.ndarray) -> np.ndarray:
    """The depth map every DEPTH_STRIDE pixels (nearest), float16, as keyframes keep it."""
    return np.asarray(depth, np.float32)[::DEPTH_STRIDE, ::DEPTH_STRIDE].astype(np.float16)


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


def depth_edges(depth: np.ndarray, rel_jump: float = 0.05, dilate: int = 2) -> np.ndarray:
    """Pixels within ``dilate`` px of a depth discontinuity: a relative step > ``rel_jump``
    between 4-neighbours, or a valid pixel next to a missing one.  (H, W) bool."""
    import cv2

    d = np.asarray(depth, np.float32)
    valid = d > 0
    pad = np.pad(d, 1, mode="edge")
    jump = np.zeros_like(valid)
    for dy, dx in ((0, 1), (1, 0), (1, 2), (2, 1)):
        nb = pad[dy:dy + d.shape[0], dx:dx + d.shape[1]]
        jump |= (np.abs(nb - d) > rel_jump * np.maximum(d, nb)) & (nb > 0) & valid
        jump |= valid & (nb <= 0)
    if dilate <= 0:
        return jump
    k = 2 * int(dilate) + 1
    return cv2.dilate(jump.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
