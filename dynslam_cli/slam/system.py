"""The SLAM system: the shared state (:mod:`~dynslam_cli.slam.state`: camera, neural map, keyframes,
poses) composed with a frontend (:mod:`~dynslam_cli.slam.frontend`: camera poses from the keyframe
backend, ``tracking.backend``, else Co-SLAM's dense tracking against the frozen neural map) and a
mapper (:mod:`~dynslam_cli.slam.mapper`: keyframes with stored rays, bundle adjustment of the neural
map and, without the backend, of the keyframe poses); :mod:`~dynslam_cli.slam.render` gives views,
observed points and the mesh.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from dynslam_cli.errors import DynslamError
from dynslam_cli.slam import render as views
from dynslam_cli.slam.frontend import Frontend, TrackResult, first_pose
from dynslam_cli.slam.mapper import AUTO_MARGIN, MapResult, Mapper, auto_bounds
from dynslam_cli.slam.state import SlamState

__all__ = ["SLAM", "FrameResult", "MapResult", "TrackResult", "auto_bounds"]


@dataclass
class FrameResult:
    index: int
    timestamp: float
    pose_c2w: np.ndarray
    track: TrackResult
    map: Optional[MapResult]
    ms: float = 0.0


class SLAM(SlamState):
    """One frame at a time: ``track`` (frontend), ``map`` (mapper), or both with ``process``;
    ``finish`` after the last; then ``trajectory`` and ``extract_mesh``."""

    def __init__(self, cfg, intrinsics, device: torch.device, bounds=None, depth_noise=None):
        super().__init__(cfg, intrinsics, device, bounds, depth_noise)
        self.frontend = Frontend(self)
        self.mapper = Mapper(self)

    @property
    def last_icp(self):
        """ICPResult of the last tracked frame (diagnostics; None when ICP did not run)."""
        return self.frontend.last_icp

    # ------------------------------------------------------------------ per frame
    def predict_pose(self) -> np.ndarray:
        """The next frame's pose predicted by the constant-velocity model (before it is tracked)."""
        return self.frontend.predict_pose()

    def track(self, frame, mask: Optional[np.ndarray] = None) -> TrackResult:
        """Track the next frame (pixels where ``mask`` is False are not used); the first frame
        builds the map (over map.bounds, else the first frame's points plus a margin)."""
        t0 = time.perf_counter()
        cur = self.prepare(frame, mask)
        if self.n_frames == 0 and self.model is None:
            b = self.bounds if self.bounds is not None else auto_bounds(frame, self.intr, first_pose(frame), AUTO_MARGIN)
            self.mapper.build_model(b)
        return self.frontend.track(frame, cur, t0)

    def reprojection_evidence(self):
        """The backend's matched keypoints of the last tracked frame and whether each reprojects at
        its pose (:meth:`~dynslam_cli.backend.backend.Backend.reprojection_evidence`); None without
        the backend or where it did not track the frame against its local map."""
        return None if self.backend is None else self.backend.reprojection_evidence()

    def retrack(self, frame, mask: Optional[np.ndarray] = None) -> TrackResult:
        """Track the last tracked frame again (e.g. with a corrected static mask), replacing its
        pose; must come between track() and map() of that frame."""
        return self.frontend.retrack(frame, mask)

    def map(self, frame, mask: Optional[np.ndarray] = None, instance_ids: Optional[np.ndarray] = None) -> Optional[MapResult]:
        """Bundle adjustment when due, then keyframe insertion when due, for the last tracked frame."""
        cur = self.cur
        if cur is None or cur.idx != self.n_frames - 1:
            raise DynslamError("SLAM.map() must follow track() of the same frame")
        self.frontend.set_mask(cur, mask)
        res = self.mapper.map(frame, cur, instance_ids)
        if self.online is not None:  # the frame's pose as it leaves the frame's processing (its keyframe's BA included)
            self.online.append(self.poses[cur.idx].copy())
        return res

    def process(self, frame, mask=None, instance_ids=None) -> FrameResult:
        t0 = time.perf_counter()
        tr = self.track(frame, mask)
        mr = self.map(frame, mask, instance_ids)
        idx = self.n_frames - 1
        return FrameResult(idx, self.timestamps[idx], self.poses[idx].copy(), tr, mr,
                           (time.perf_counter() - t0) * 1000)

    def finish(self) -> Optional[MapResult]:
        """After the last frame: the backend's bundle adjustment of every keyframe (which moves the
        frames tracked against them too), then mapping.final_iters more bundle adjustment iterations
        of the neural map over all keyframes and the last tracked frame (the periodic BA's code path;
        its MapResult, None when off)."""
        if self.backend is not None:
            self.backend.finish()
        return self.mapper.finish()

    def ba_ray_indices(self, cur, iters: int, n_rays: int, use_keyframes: bool = True):
        """Rays for ``iters`` BA iterations (see :meth:`Mapper.ba_ray_indices`)."""
        return self.mapper.ba_ray_indices(cur, iters, n_rays, use_keyframes)

    # ------------------------------------------------------------------ outputs
    def trajectory(self) -> np.ndarray:
        """(N, 4, 4) c2w; non-keyframes re-expressed relative to their refined keyframe (the
        backend's bundle-adjusted trajectory when it tracks)."""
        if self.backend is not None:
            return self.backend.trajectory()[:self.n_frames].copy()
        out = np.zeros((self.n_frames, 4, 4))
        for i in range(self.n_frames):
            out[i] = self.pose_of(i)
        return out

    def final_trajectory(self) -> tuple[np.ndarray, int]:
        """The trajectory to write once the sequence is finished: the backend's with every frame but
        the keyframes solved again against the finished map (``Backend.refined_trajectory``), else
        :meth:`trajectory`; and how many frames were solved again."""
        if self.backend is None:
            return self.trajectory(), 0
        traj, n = self.backend.refined_trajectory()
        return traj[:self.n_frames].copy(), n

    def render(self, pose_c2w: np.ndarray, scale: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
        """Depth (h×w, m; 0 = no surface) and colour (h×w×3 uint8) rendered at ``scale`` resolution
        without depth guidance (:func:`~dynslam_cli.slam.render.render_view`)."""
        if self.model is None:
            raise DynslamError("render() needs a map: process a frame first")
        return views.render_view(self.model, self.cfg.map, self.intr, pose_c2w, scale, self.device)

    def observed_points(self, max_points: int = 2_000_000) -> np.ndarray:
        return views.observed_points(self.keyframes, self.intr, max_points)

    def extract_mesh(self, voxel: float):
        if self.model is None:
            raise DynslamError("extract_mesh() needs a map: process a frame first")
        return views.extract_mesh(self.model, self.keyframes, self.intr, voxel, self.device)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        prev_depth = self.frontend.prev_depth
        return {
            "version": 1,
            "bounds": None if self.bounds is None else self.bounds.copy(),
            "model": None if self.model is None else {k: v.detach().cpu().clone() for k, v in self.model.state_dict().items()},
            "map_opt": None if self.map_opt is None else self.map_opt.state_dict(),
            "keyframes": self.keyframes.state_dict(),
            "poses": np.array(self.poses).reshape(-1, 4, 4),
            "rel": [None if r is None else r.copy() for r in self.rel],
            "kf_of": list(self.kf_of),
            "timestamps": list(self.timestamps),
            "events": list(self.events),
            "online": None if self.online is None else np.array(self.online).reshape(-1, 4, 4),
            "rng": self.rng.bit_generator.state,
            "tgen": self.tgen.get_state().cpu(),
            "prev_depth": None if prev_depth is None else prev_depth.copy(),
            "backend": None if self.backend is None else self.backend.state_dict(),
        }

    def load_state_dict(self, d: dict) -> None:
        if d.get("bounds") is not None:
            self.mapper.build_model(np.asarray(d["bounds"]))
            self.model.load_state_dict(d["model"])
            if d.get("map_opt") is not None:
                self.map_opt.load_state_dict(d["map_opt"])
        self.keyframes.load_state_dict(d["keyframes"])
        self.poses = [np.array(p, np.float64) for p in d["poses"]]
        self.rel = [None if r is None else np.array(r) for r in d["rel"]]
        self.kf_of = list(d["kf_of"])
        self.timestamps = list(d["timestamps"])
        self.events = list(d["events"])
        online = d.get("online")  # a checkpoint from before: the earlier frames' online poses are not known
        self.online = None if online is None else [np.array(p, np.float64) for p in online]
        self.rng.bit_generator.state = d["rng"]
        self.tgen.set_state(d["tgen"])
        self.cur = None
        pd = d.get("prev_depth")
        self.frontend.prev_depth = None if pd is None else np.asarray(pd, np.float32)
        self.backend = None
        if d.get("backend") is not None:
            self.make_backend().load_state_dict(d["backend"])
