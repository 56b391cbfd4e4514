"""The state the SLAM system's parts share (DROID-SLAM's frame buffer): camera, neural map, keyframes,
every frame's pose, the random generators, the current frame and the tracking events.

:class:`~dynslam_cli.slam.frontend.Frontend` (tracking), :class:`~dynslam_cli.slam.mapper.Mapper`
(the neural map's optimisation) and :class:`~dynslam_cli.slam.system.SLAM` (which composes them and
is this state) read and write it through these public members only.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch

from dynslam_cli.backend.backend import Backend
from dynslam_cli.errors import DynslamError
from dynslam_cli.geometry.camera import pixel_dirs
from dynslam_cli.map.model import NeuralMap
from dynslam_cli.slam.keyframes import KeyframeStore, depth_edges, valid_pixels
from dynslam_cli.utils.adam import Adam

log = logging.getLogger(__name__)

# Fewer usable pixels than this: dense tracking is skipped (constant-velocity pose, logged), and depth edges are not
# taken out of a pixel set (without_edges).
MIN_PIXELS = 50
# Tracking, ICP and mapping rays avoid pixels within this many pixels of a depth discontinuity (a step of >5 % at
# 540 px focal length, or a hole): the map blurs edges, and on real depth they bias the pose.
EDGE_MARGIN = 2


@dataclass
class CurrentFrame:
    """The frame being tracked and mapped, as tensors and arrays."""

    idx: int
    timestamp: float
    rgb: torch.Tensor     # (H*W, 3) float32 in [0, 1]
    depth: torch.Tensor   # (H*W,) float32
    depth_np: np.ndarray
    rgb_np: np.ndarray
    valid: np.ndarray     # flat indices usable for sampling
    mask: Optional[np.ndarray]
    extra: dict = field(default_factory=dict)

    def edges(self, margin: int, fx: float) -> np.ndarray:
        """Depth-edge pixels within ``margin`` px (cached per margin).

        A step counts as an edge when it exceeds 5 % of the depth at a 540 px focal length (about
        0.1 degrees per pixel; only surfaces seen at more than ~88 degrees step that much), scaled
        with the pixel's angular size (focal length ``fx``) so that wide, low-resolution cameras do
        not see every oblique wall as an edge."""
        cache = self.extra.setdefault("edges", {})
        if margin not in cache:
            cache[margin] = depth_edges(self.depth_np, max(0.05, 27.0 / float(fx)), margin)
        return cache[margin]

    def without_edges(self, pixels: np.ndarray, margin: int, fx: float) -> np.ndarray:
        """``pixels`` (flat indices) without depth-edge pixels, unless that leaves fewer than
        MIN_PIXELS (then all of them)."""
        if margin <= 0 or len(pixels) == 0:
            return pixels
        sub = pixels[~self.edges(margin, fx).reshape(-1)[pixels]]
        return sub if len(sub) >= MIN_PIXELS else pixels

    def masked_depth(self) -> np.ndarray:
        """The depth of the usable (static) pixels; 0 elsewhere."""
        return self.depth_np if self.mask is None else np.where(self.mask, self.depth_np, 0).astype(np.float32)

    def icp_depth(self, fx: float) -> np.ndarray:
        """The depth ICP aligns: static pixels, without depth edges (EDGE_MARGIN)."""
        return np.where(self.edges(EDGE_MARGIN, fx), 0, self.masked_depth()).astype(np.float32)


class SlamState:
    """Camera, map, keyframes, poses and generators shared by tracking and mapping."""

    def __init__(self, cfg, intrinsics, device: torch.device, bounds=None, depth_noise: Optional[float] = None):
        self.cfg = cfg
        # the sensor's depth noise per metre^2 the backend weighs depth by (Sequence.depth_noise; None = the default)
        self.depth_noise = depth_noise
        self.intr = intrinsics
        self.device = torch.device(device)
        self.H, self.W = int(intrinsics.height), int(intrinsics.width)
        self.bounds = None if bounds is None else np.asarray(bounds, np.float64)
        self.model: Optional[NeuralMap] = None
        self.map_opt: Optional[Adam] = None
        self.keyframes = KeyframeStore()  # the neural map's and the backend's keyframes, their instances
        self.poses: list[np.ndarray] = []       # latest estimate of every frame (c2w)
        self.rel: list[Optional[np.ndarray]] = []  # pose relative to its keyframe at tracking time
        self.kf_of: list[int] = []               # keyframe frame id each frame is expressed against
        self.timestamps: list[float] = []
        self.events: list[dict] = []
        self.online: Optional[list[np.ndarray]] = []  # each frame's pose when it was done (None: not all known)
        seed = int(cfg.run.seed)
        self.rng = np.random.default_rng(seed)
        self.tgen = torch.Generator(device=self.device)
        self.tgen.manual_seed(seed)
        vv, uu = np.mgrid[0:self.H, 0:self.W]
        self.uv = np.stack([uu.ravel(), vv.ravel()], 1).astype(np.int32)  # (H*W, 2) pixel of each flat index
        self.dirs = torch.from_numpy(pixel_dirs(uu.ravel(), vv.ravel(), intrinsics.fx, intrinsics.fy,
                                                intrinsics.cx, intrinsics.cy)).to(self.device)
        self.cur: Optional[CurrentFrame] = None  # the last tracked frame
        self.backend: Optional[Backend] = None  # the keyframe backend (tracking.backend), made on frame 0

    @property
    def n_frames(self) -> int:
        return len(self.poses)

    def t(self, a, dtype=torch.float32) -> torch.Tensor:
        """``a`` as a tensor on the device."""
        return torch.as_tensor(np.asarray(a), dtype=dtype).to(self.device)

    def sample(self, valid: np.ndarray, n: int) -> np.ndarray:
        """``n`` flat indices drawn with replacement from ``valid`` (the shared generator)."""
        return valid[self.rng.integers(0, len(valid), size=n)]

    def prepare(self, frame, mask) -> CurrentFrame:
        """The frame as the next one to track (index n_frames); its image size must match the camera."""
        depth = np.asarray(frame.depth, np.float32)
        rgb = np.asarray(frame.rgb)
        if depth.shape != (self.H, self.W) or rgb.shape[:2] != (self.H, self.W):
            raise DynslamError(f"frame {getattr(frame, 'index', '?')}: image size {rgb.shape[:2]}/{depth.shape} "
                               f"does not match the intrinsics {self.H}x{self.W}")
        depth = np.where(np.isfinite(depth), depth, 0).astype(np.float32)
        valid = valid_pixels(depth, mask, self.cfg.tracking.ignore_border)
        return CurrentFrame(
            idx=self.n_frames, timestamp=float(getattr(frame, "timestamp", self.n_frames)),
            rgb=torch.from_numpy(rgb.reshape(-1, 3)).to(self.device).float().div_(255.0),
            depth=torch.from_numpy(depth.reshape(-1)).to(self.device),
            depth_np=depth, rgb_np=rgb, valid=valid, mask=None if mask is None else np.asarray(mask, bool))

    def set_map_grad(self, on: bool) -> None:
        for p in self.model.parameters():
            p.requires_grad_(on)

    def make_backend(self, first_pose=None) -> Backend:
        """A keyframe backend for this camera (tracking.backend); stored as ``backend``."""
        i = self.intr
        kw = {} if first_pose is None else {"first_pose": first_pose}
        self.backend = Backend((i.fx, i.fy, i.cx, i.cy, self.W, self.H), self.cfg.backend, depth_noise=self.depth_noise,
                               keyframes=self.keyframes.landmark_keyframes, **kw)  # forgetting reaches its landmarks
        return self.backend

    def event(self, idx: int, kind: str, detail: str) -> None:
        """Log a tracking event (tracking_events.json)."""
        self.events.append({"frame": int(idx), "kind": kind, "detail": detail})
        log.warning("frame %d: tracking %s (%s); using the constant-velocity pose", idx, kind, detail)

    def pose_of(self, i: int) -> np.ndarray:
        """Frame ``i``'s pose as the trajectory has it (relative to its keyframe, which bundle
        adjustment refines)."""
        r = self.rel[i]
        return self.poses[i] if r is None else self.poses[self.kf_of[i]] @ r

    def sync_backend_poses(self) -> None:
        """Every tracked frame's and keyframe's pose from the backend's bundle-adjusted trajectory."""
        traj = self.backend.trajectory()
        for i in range(min(len(traj), len(self.poses))):
            self.poses[i] = traj[i].copy()
        for k in self.keyframes:
            if k.frame_id < len(traj):
                k.pose_c2w = traj[k.frame_id].copy()
