"""Per-frame tracking: the keyframe backend's pose (``tracking.backend``), or Co-SLAM's dense
tracking against the frozen neural map from a constant-velocity guess refined by ICP (the
``coslam`` / ``paper`` presets, and any frame the backend loses); re-tracking with a corrected mask;
divergence and rejected-guess events.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from dynslam_cli.errors import DynslamError
from dynslam_cli.geometry.icp import icp_depth
from dynslam_cli.geometry.lie import inv_np, orthonormalize, se3_exp
from dynslam_cli.map.losses import ray_losses
from dynslam_cli.map.render import n_samples, render_rays, sample_depths
from dynslam_cli.slam.keyframes import valid_pixels
from dynslam_cli.slam.state import EDGE_MARGIN, MIN_PIXELS, CurrentFrame, SlamState
from dynslam_cli.utils.adam import Adam

log = logging.getLogger(__name__)

# A tracked pose moving more than this (m) from its initial guess is divergence; an ICP initial guess farther than
# this from the constant-velocity one is not used.
MAX_JUMP = 0.3
# ICP initial guess (tracking.icp_init): pyramid downsampling factors, coarse to fine (640x480 -> 80x60, 160x120,
# 320x240), and Gauss-Newton iterations per level.
ICP_FACTORS = (8, 4, 2)
ICP_ITERS = (8, 5, 3)
# ICP: at most about this many current points per level (an even stride); 0 = all. 20000 halves ICP time but cost
# 0.1-0.4 cm ATE on Bonn crowd frames 0-39.
ICP_MAX_POINTS = 0
# ICP: associations farther apart than this (m) are rejected.
ICP_MAX_DIST = 0.1
# ICP result ignored (constant-velocity guess kept) when fewer of the current points associate.
ICP_MIN_FRACTION = 0.2


@dataclass
class TrackResult:
    pose_c2w: np.ndarray
    loss: float
    iters: int
    diverged: bool
    ms: float
    reason: str = ""  # the backend's: motion | wide | relocalised | first (+ "; keyframe (why)"); dense tracking's failure
    inliers: int = 0  # the backend's static inliers (0 where dense tracking took over)


def first_pose(frame) -> np.ndarray:
    """The first frame's pose: its ground truth where it has one (the trajectory's frame), else identity."""
    gt = getattr(frame, "pose_c2w", None)
    return np.array(gt, np.float64) if gt is not None else np.eye(4)


def off_velocity(cand: np.ndarray, rel: np.ndarray) -> float:
    """Distance (m) between the translations of an initial-guess step ``cand`` (previous camera
    <- current) and the constant-velocity step ``rel``."""
    return float(np.linalg.norm(cand[:3, 3] - rel[:3, 3]))


class Frontend:
    """Tracks each frame into the shared state: appends its pose, timestamp and keyframe reference."""

    def __init__(self, state: SlamState):
        self.s = state
        self.prev_depth: Optional[np.ndarray] = None  # last tracked frame's (masked) depth, ICP reference
        self._undo: Optional[tuple] = None  # (ICP reference,) before the last track(), for retrack()
        self.last_icp = None  # ICPResult of the last tracked frame (diagnostics)

    # ------------------------------------------------------------------ initial guess
    def predict_pose(self) -> np.ndarray:
        """The next frame's pose predicted by the constant-velocity model (before it is tracked)."""
        return self.initial_guess()

    def initial_guess(self, cur: Optional[CurrentFrame] = None) -> np.ndarray:
        """The current frame's initial pose: constant velocity, refined by ICP against the previous
        frame's depth (tracking.icp_init) where that converges near it."""
        s = self.s
        p1 = s.poses[-1]
        rel = np.eye(4)  # previous camera <- current camera
        if len(s.poses) >= 2:
            rel = inv_np(s.poses[-2]) @ p1
        self.last_icp = None
        if s.cfg.tracking.icp_init and cur is not None and self.prev_depth is not None:
            i = s.intr
            res = icp_depth(self.prev_depth, cur.icp_depth(i.fx), (i.fx, i.fy, i.cx, i.cy),
                            init=rel, factors=ICP_FACTORS, iters=ICP_ITERS, max_dist=ICP_MAX_DIST,
                            min_fraction=ICP_MIN_FRACTION, max_points=ICP_MAX_POINTS)
            self.last_icp = res
            if res.ok and self.plausible(res.T, rel, "ICP", cur.idx):
                rel = res.T
        return orthonormalize(p1 @ rel)

    def plausible(self, cand: np.ndarray, rel: np.ndarray, source: str, idx: int) -> bool:
        """Whether an initial-guess step ``cand`` lies within ``MAX_JUMP`` of the
        constant-velocity step ``rel``; a rejected one is logged as a ``guess_rejected`` event
        (tracking_events.json)."""
        off = off_velocity(cand, rel)
        if off <= MAX_JUMP:
            return True
        detail = f"{source} step {off:.3f} m from constant velocity > {MAX_JUMP} m"
        self.s.events.append({"frame": int(idx), "kind": "guess_rejected", "detail": detail})
        log.info("frame %d: %s", idx, detail)
        return False

    # ------------------------------------------------------------------ tracking
    def track(self, frame, cur: CurrentFrame, t0: float) -> TrackResult:
        """Track the prepared frame ``cur`` (the next one; on frame 0 the map must exist)."""
        s = self.s
        s.cur = cur
        if s.n_frames == 0:
            pose = first_pose(frame)
            reason, inliers = "", 0
            if s.cfg.tracking.backend:
                s.make_backend(first_pose=pose)
                out = self._backend_track(frame, cur)
                reason, inliers = out.reason, out.inliers
            return self._finish(cur, pose, 0.0, 0, False, t0, reason, inliers)
        iters = int(s.cfg.tracking.iters)
        if s.backend is not None:
            out = self._backend_track(frame, cur)
            if not out.lost:
                return self._finish(cur, out.pose_c2w, float("nan"), 0, False, t0, out.reason, out.inliers)
            # lost: dense tracking against the neural map from the constant-velocity pose (if it runs)
            s.event(cur.idx, "lost", out.reason + ("; dense tracking from constant velocity" if iters > 0 else ""))
            init = out.pose_c2w
        else:
            init = self.initial_guess(cur)
        tvalid = cur.without_edges(cur.valid, EDGE_MARGIN, s.intr.fx)
        if len(tvalid) < MIN_PIXELS or iters <= 0:
            reason = f"only {len(tvalid)} usable pixels" if iters > 0 else ""
            if reason:
                s.event(cur.idx, "skipped", reason)
            return self._finish(cur, init, float("nan"), 0, bool(reason), t0, reason)
        pose, best_loss, bad = self.dense_track(cur, tvalid, init, iters)
        if bad:
            s.event(cur.idx, "diverged", bad)
            return self._finish(cur, init, best_loss, iters, True, t0, bad)
        return self._finish(cur, pose, best_loss, iters, False, t0)

    def dense_track(self, cur: CurrentFrame, tvalid: np.ndarray, init: np.ndarray, iters: int):
        """Co-SLAM tracking of ``cur`` against the frozen map from ``init``, on rays drawn from
        ``tvalid``: (pose, lowest loss, why it diverged or "")."""
        s = self.s
        tc = s.cfg.tracking
        R, S = tc.n_rays, n_samples(s.cfg.map)
        idx = torch.from_numpy(s.sample(tvalid, iters * R)).to(s.device)  # new rays every iteration (Co-SLAM)
        dirs_c = s.dirs[idx].view(iters, R, 3)
        rgb_t = cur.rgb[idx].view(iters, R, 3)
        d_t = cur.depth[idx]
        z_all = sample_depths(d_t, s.cfg.map, s.tgen).view(iters, R, S)
        d_t = d_t.view(iters, R)
        T0 = s.t(init)
        xi = torch.zeros(6, device=s.device, requires_grad=True)
        opt = Adam([xi], lr=tc.lr)
        best_loss, best_xi = float("inf"), torch.zeros(6, device=s.device)
        s.set_map_grad(False)
        bad = ""
        try:
            for it in range(iters):
                T = T0 @ se3_exp(xi)
                o = T[:3, 3].unsqueeze(0)
                d = dirs_c[it] @ T[:3, :3].T
                out = render_rays(s.model, o, d, z_all[it])
                loss = ray_losses(out, z_all[it], rgb_t[it], d_t[it], s.cfg.map).total
                lv = float(loss.detach())
                if not np.isfinite(lv):
                    bad = f"non-finite loss at iteration {it}"
                    break
                if lv < best_loss:
                    best_loss = lv
                    best_xi = xi.detach().clone()
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
        finally:
            s.set_map_grad(True)
        pose = init @ se3_exp(best_xi.double().cpu()).numpy()
        jump = float(np.linalg.norm(pose[:3, 3] - init[:3, 3]))
        if not bad and (not np.all(np.isfinite(pose)) or best_loss == float("inf")):
            bad = "non-finite pose"
        if not bad and jump > MAX_JUMP:
            bad = f"jump of {jump:.3f} m > {MAX_JUMP} m"
        return (init if bad else orthonormalize(pose)), best_loss, bad

    def _backend_track(self, frame, cur: CurrentFrame):
        """The backend's pose of the current frame (static pixels; the depth before the data layer's
        depth cut, where the frame has it, as keypoints beyond it still fix the pose).  A keyframe it
        finds due is inserted by map(), with the frame's final static mask."""
        full = getattr(frame, "depth_full", None)
        depth = cur.depth_np if full is None else np.where(np.isfinite(full), full, 0).astype(np.float32)
        return self.s.backend.track(cur.idx, cur.rgb_np, depth, cur.mask, defer=True, stamp=cur.timestamp)

    def retrack(self, frame, mask: Optional[np.ndarray] = None) -> TrackResult:
        """Track the last tracked frame again (e.g. with a corrected static mask), replacing its
        pose; must come between track() and map() of that frame."""
        s = self.s
        cur = s.cur
        if cur is None or cur.idx != s.n_frames - 1 or cur.idx == 0 or self._undo is None:
            raise DynslamError("SLAM.retrack() must follow track() of the same frame (not the first)")
        if s.backend is not None:  # the backend re-tracks on the keypoints still static; the mask reaches map()
            t0 = time.perf_counter()
            pose = None if mask is None else s.backend.retrack(np.asarray(mask, bool))
            if pose is not None:
                s.poses[-1] = orthonormalize(pose)
            return TrackResult(s.poses[-1].copy(), float("nan"), 0, False, (time.perf_counter() - t0) * 1000,
                               "backend re-tracked" if pose is not None else "backend pose kept")
        for lst in (s.poses, s.timestamps, s.kf_of, s.rel):
            lst.pop()
        self.prev_depth = self._undo[0]
        t0 = time.perf_counter()
        return self.track(frame, s.prepare(frame, mask), t0)

    def _finish(self, cur, pose, loss, iters, diverged, t0, reason="", inliers=0) -> TrackResult:
        s = self.s
        ke = s.cfg.mapping.keyframe_every
        self._undo = (self.prev_depth,)
        if s.backend is not None and cur.idx > 0:  # a lost frame's pose came from dense tracking
            s.backend.correct_last(pose)
        if s.backend is None:
            self.prev_depth = cur.icp_depth(s.intr.fx) if s.cfg.tracking.icp_init else None
        s.poses.append(np.array(pose, np.float64))
        s.timestamps.append(cur.timestamp)
        kf_id = (cur.idx // ke) * ke
        s.kf_of.append(kf_id)
        if kf_id < cur.idx and s.backend is None:
            s.rel.append(inv_np(s.poses[kf_id]) @ s.poses[cur.idx])
        else:
            s.rel.append(None)
        return TrackResult(s.poses[-1].copy(), float(loss), int(iters), bool(diverged),
                           (time.perf_counter() - t0) * 1000, reason, int(inliers))

    def set_mask(self, cur: CurrentFrame, mask: Optional[np.ndarray]) -> None:
        """The static mask map() trains on (the loop's: the frame's mask from before its check): the
        frame's usable pixels, and the next frame's ICP reference, follow it."""
        if mask is not None and (cur.mask is None or not np.array_equal(np.asarray(mask, bool), cur.mask)):
            cur.valid = valid_pixels(cur.depth_np, mask, self.s.cfg.tracking.ignore_border)
            cur.mask = np.asarray(mask, bool)
            if self.s.cfg.tracking.icp_init and self.s.backend is None:  # the next ICP aligns to the static pixels
                self.prev_depth = cur.icp_depth(self.s.intr.fx)
