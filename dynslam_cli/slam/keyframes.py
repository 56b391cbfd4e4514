"""The keyframe store: the neural map's keyframes, each keeping a random subset of its pixels as
rays for replay, and the backend's keyframes with their landmarks.

Per stored ray: pixel (u, v), colour, depth, instance id (int32, -1 = none) and a mutable
``usable`` flag (False = the dynamic module excluded the ray; bundle adjustment skips it).
:class:`KeyframeStore` holds the keyframes of a run with what learning to forget needs of them:
the instances of each keyframe (the classifier's features, the class prior), and the backend's
keyframes (:class:`~dynslam_cli.backend.keyframes.LandmarkKeyframes`: poses, landmarks, the
instance each landmark was made on), whose landmarks on an instance found to move are left out
through the store.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dynslam_cli.backend.keyframes import LandmarkKeyframes
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
    # kept): what the camera saw, for motion.stayed.stationary_instances
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


class KeyframeStore:
    """The neural map's keyframes of a run (a sequence: ``len``, iteration, indexing and slices as
    a list), the backend's keyframes and landmarks (``landmark_keyframes``, which the backend
    builds; empty without one) and, for the frames whose instances were registered (keyframes of
    either kind), the instances' classifier features and class prior."""

    def __init__(self):
        self._frames: list[Keyframe] = []
        self._instances: dict[int, dict] = {}
        self.landmark_keyframes = LandmarkKeyframes()

    def __len__(self) -> int:
        return len(self._frames)

    def __iter__(self):
        return iter(self._frames)

    def __getitem__(self, i):
        return self._frames[i]

    def add(self, kf: Keyframe) -> Keyframe:
        self._frames.append(kf)
        return kf

    # -- rays --------------------------------------------------------------------------------------
    def usable_rays(self) -> np.ndarray:
        """Indices of the usable rays into all keyframes' rays in keyframe order."""
        if not self._frames:
            return np.zeros(0, np.int64)
        return np.flatnonzero(np.concatenate([k.usable for k in self._frames]))

    def gather(self, idx: np.ndarray) -> tuple:
        """Rays ``idx`` (indices into all keyframes' rays in keyframe order): pixels (N×2 int64),
        colours (N×3 uint8), depths (N float32) and the keyframe each belongs to (N int64), gathered
        from the keyframes' own arrays (nothing is copied for the rays not asked for)."""
        idx = np.asarray(idx, np.int64)
        start = np.cumsum([0] + [len(k) for k in self._frames])
        owner = np.searchsorted(start, idx, side="right") - 1
        if len(idx) and (idx.min() < 0 or idx.max() >= start[-1]):
            raise IndexError(f"keyframe ray index out of range 0..{start[-1] - 1}")
        local = idx - start[owner]
        uv = np.empty((len(idx), 2), np.int64)
        rgb = np.empty((len(idx), 3), np.uint8)
        depth = np.empty(len(idx), np.float32)
        order = np.argsort(owner, kind="stable")  # one keyframe at a time
        bounds = np.searchsorted(owner[order], np.arange(len(self._frames) + 1))
        for o in np.flatnonzero(np.diff(bounds)):
            rows = order[bounds[o]:bounds[o + 1]]
            k, at = self._frames[o], local[rows]
            uv[rows], rgb[rows], depth[rows] = k.pixels[at], k.rgb[at], k.depth[at]
        return uv, rgb, depth, owner

    # -- instances and forgetting --------------------------------------------------------------------
    def register_instances(self, frame_id: int, feats: np.ndarray, prior: np.ndarray) -> None:
        """Frame ``frame_id``'s instances (id i+1 for row i): classifier features and class prior."""
        self._instances[int(frame_id)] = {"feats": np.asarray(feats, np.float32).copy(),
                                          "prior": np.asarray(prior, bool).copy()}

    def has_instances(self, frame_id: int) -> bool:
        return int(frame_id) in self._instances

    def instances(self) -> dict:
        """Frame id -> {"feats", "prior"} of every registered frame, in registration order."""
        return self._instances

    def forget(self, dynamic: dict) -> int:
        """``dynamic``: frame id -> the instance ids now called dynamic, for every registered frame.
        The landmarks a backend keyframe made on them are left out (those of instances called static
        again come back); every keyframe's usable rays are recomputed (rays of, or within the mask
        dilation of, a dynamic instance; rays seen gone stay unusable; rays of instances called
        static again are usable again).  Returns rays masked."""
        for fid, dyn_ids in dynamic.items():
            self.landmark_keyframes.forget(fid, dyn_ids)
        masked = 0
        for kf in self._frames:
            if kf.frame_id not in dynamic:
                continue
            dyn_ids = dynamic[kf.frame_id]
            kf.usable = ~np.isin(kf.instance_ids, dyn_ids)
            if kf.near_ids is not None:  # rays within the mask dilation of a dynamic instance
                kf.usable &= ~np.isin(kf.near_ids, dyn_ids).any(axis=1)
            if kf.gone is not None:  # surfaces seen gone stay forgotten
                kf.usable &= ~kf.gone
            masked += int((~kf.usable).sum())
        return masked

    # -- checkpoints ----------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"keyframes": [k.to_dict() for k in self._frames],
                "instances": {k: {"feats": v["feats"].copy(), "prior": v["prior"].copy()}
                              for k, v in self._instances.items()},
                "landmark_keyframes": self.landmark_keyframes.state_dict()}

    def load_state_dict(self, d: dict) -> None:
        self._frames = [Keyframe.from_dict(k) for k in d["keyframes"]]
        self._instances = {}
        for k, v in d["instances"].items():
            self.register_instances(int(k), np.asarray(v["feats"]), np.asarray(v["prior"]))
        self.landmark_keyframes.load_state_dict(d["landmark_keyframes"])  # in place: a backend holds it


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

    from dynslam_cli.slam._edge_kernels import depth_jumps

    jump = depth_jumps(np.ascontiguousarray(depth, np.float32), float(rel_jump))
    if dilate <= 0:
        return jump
    k = 2 * int(dilate) + 1
    return cv2.dilate(jump.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
