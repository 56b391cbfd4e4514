"""The SLAM system: camera poses from the keyframe backend (``tracking.backend``; else Co-SLAM's
dense tracking against the frozen neural map), keyframes with stored rays, bundle adjustment of the
neural map (and, without the backend, of the keyframe poses).

Every ray sampler takes a per-pixel mask (H×W bool, True = usable); the dynamic module passes its
static mask and later refreshes ``keyframes[k].usable``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch

from dynslam_cli.backend.backend import Backend
from dynslam_cli.errors import DynslamError
from dynslam_cli.geometry.camera import backproject, pixel_dirs
from dynslam_cli.geometry.icp import icp_depth
from dynslam_cli.geometry.lie import inv_np, orthonormalize, se3_exp
from dynslam_cli.map.losses import ray_losses, smoothness_points, smoothness_tv
from dynslam_cli.map.model import NeuralMap
from dynslam_cli.map.render import render_rays, sample_depths
from dynslam_cli.slam.keyframes import Keyframe, depth_edges, subsample_depth, valid_pixels

log = logging.getLogger(__name__)

# Margin (m) added around the first frame's points when map.bounds is null.
AUTO_MARGIN = 2.0
# A tracked pose moving more than this (m) from its initial guess is divergence; an ICP initial guess farther than
# this from the constant-velocity one is not used.
MAX_JUMP = 0.3
# Fewer usable pixels than this: dense tracking is skipped (constant-velocity pose, logged).
MIN_PIXELS = 50
# Tracking, ICP and mapping rays avoid pixels within this many pixels of a depth discontinuity (a step of >5 % at
# 540 px focal length, or a hole): the map blurs edges, and on real depth they bias the pose.
EDGE_MARGIN = 2
# Dense tracking draws new rays every iteration (Co-SLAM) and returns the lowest-loss pose seen.
RESAMPLE_RAYS = True
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
# Rays per mapping iteration on the first frame.
FIRST_RAYS = 2048
# At least this many of the BA rays come from the current frame (Co-SLAM min_pixels_cur).
MIN_RAYS_CURRENT = 100
# Bundle adjustment steps the pose optimiser once every N iterations on the gradients summed over them (Co-SLAM
# pose_accum_step); the map steps every iteration.  The first keyframe's pose stays fixed, the current frame's is
# refined with the keyframes' (Co-SLAM optim_cur).
POSE_ACCUM_STEPS = 5
# render() (the dynamic check) without depth: coarse samples over [near, far], then fine samples around the first
# surface crossing (32 / 8 at check resolution; Co-SLAM renders 64 / 16).
RENDER_COARSE = 32
RENDER_FINE = 8


@dataclass
class TrackResult:
    pose_c2w: np.ndarray
    loss: float
    iters: int
    diverged: bool
    ms: float
    reason: str = ""


@dataclass
class MapResult:
    keyframe: bool
    ba: bool
    iters: int
    loss: float
    ms: float


@dataclass
class FrameResult:
    index: int
    timestamp: float
    pose_c2w: np.ndarray
    track: TrackResult
    map: Optional[MapResult]
    ms: float = 0.0


@dataclass
class _Current:
    idx: int
    timestamp: float
    rgb: torch.Tensor     # (H*W, 3) float32 in [0, 1]
    depth: torch.Tensor   # (H*W,) float32
    depth_np: np.ndarray
    rgb_np: np.ndarray
    valid: np.ndarray     # flat indices usable for sampling
    mask: Optional[np.ndarray]
    extra: dict = field(default_factory=dict)


def auto_bounds(frame, intr, pose_c2w: np.ndarray, margin: float) -> np.ndarray:
    """Bounds from the first frame's depth (world frame) plus ``margin`` on every side."""
    pts = backproject(np.asarray(frame.depth, np.float32), intr.fx, intr.fy, intr.cx, intr.cy).reshape(-1, 3)
    pts = pts[pts[:, 2] > 0]
    if len(pts) < 10:
        raise DynslamError("cannot derive map bounds: the first frame has (almost) no valid depth; set map.bounds")
    pts = pts @ pose_c2w[:3, :3].T + pose_c2w[:3, 3]
    lo = np.percentile(pts, 0.5, axis=0) - margin
    hi = np.percentile(pts, 99.5, axis=0) + margin
    cam = pose_c2w[:3, 3]
    return np.stack([np.minimum(lo, cam - margin), np.maximum(hi, cam + margin)])


class SLAM:
    def __init__(self, cfg, intrinsics, device: torch.device, bounds=None):
        self.cfg = cfg
        self.intr = intrinsics
        self.device = torch.device(device)
        self.H, self.W = int(intrinsics.height), int(intrinsics.width)
        self.bounds = None if bounds is None else np.asarray(bounds, np.float64)
        self.model: Optional[NeuralMap] = None
        self.map_opt: Optional[torch.optim.Optimizer] = None
        self.keyframes: list[Keyframe] = []
        self.poses: list[np.ndarray] = []       # latest estimate of every frame (c2w)
        self.rel: list[Optional[np.ndarray]] = []  # pose relative to its keyframe at tracking time
        self.kf_of: list[int] = []               # keyframe frame id each frame is expressed against
        self.timestamps: list[float] = []
        self.events: list[dict] = []
        seed = int(cfg.run.seed)
        self.rng = np.random.default_rng(seed)
        self.tgen = torch.Generator(device=self.device)
        self.tgen.manual_seed(seed)
        vv, uu = np.mgrid[0:self.H, 0:self.W]
        self._uv = np.stack([uu.ravel(), vv.ravel()], 1).astype(np.int32)
        self.dirs = torch.from_numpy(pixel_dirs(uu.ravel(), vv.ravel(), intrinsics.fx, intrinsics.fy,
                                                intrinsics.cx, intrinsics.cy)).to(self.device)
        self._cur: Optional[_Current] = None
        self._kf_cache = None  # concatenated keyframe rays (torch) and owners
        self._prev_depth: Optional[np.ndarray] = None  # last tracked frame's (masked) depth, ICP reference
        self._undo: Optional[tuple] = None  # (ICP reference,) before the last track(), for retrack()
        self.last_icp = None  # ICPResult of the last tracked frame (diagnostics)
        self.backend: Optional[Backend] = None  # the keyframe backend (tracking.backend), made on frame 0
        self.backend_keyframe = False  # whether the last map() inserted a backend keyframe

    # ------------------------------------------------------------------ helpers
    @property
    def n_frames(self) -> int:
        return len(self.poses)

    def _t(self, a, dtype=torch.float32) -> torch.Tensor:
        return torch.as_tensor(np.asarray(a), dtype=dtype).to(self.device)

    def _build_model(self, bounds: np.ndarray) -> None:
        self.bounds = np.asarray(bounds, np.float64)
        with torch.random.fork_rng(devices=[]):  # initialise from run.seed, leave the global RNG alone
            torch.manual_seed(int(self.cfg.run.seed))
            self.model = NeuralMap(self.cfg.map, self.bounds).to(self.device)
        kw = {"fused": True} if self.device.type in ("cpu", "cuda") else {}
        try:
            self.map_opt = torch.optim.Adam(self.model.parameters(), lr=self.cfg.mapping.lr_map,
                                            betas=(0.9, 0.99), eps=1e-15, **kw)
        except (RuntimeError, TypeError):
            self.map_opt = torch.optim.Adam(self.model.parameters(), lr=self.cfg.mapping.lr_map,
                                            betas=(0.9, 0.99), eps=1e-15)

    def _prepare(self, frame, mask, need_depth=True) -> _Current:
        depth = np.asarray(frame.depth, np.float32)
        rgb = np.asarray(frame.rgb)
        if depth.shape != (self.H, self.W) or rgb.shape[:2] != (self.H, self.W):
            raise DynslamError(f"frame {getattr(frame, 'index', '?')}: image size {rgb.shape[:2]}/{depth.shape} "
                               f"does not match the intrinsics {self.H}x{self.W}")
        depth = np.where(np.isfinite(depth), depth, 0).astype(np.float32)
        valid = valid_pixels(depth, mask, self.cfg.tracking.ignore_border)
        return _Current(
            idx=self.n_frames, timestamp=float(getattr(frame, "timestamp", self.n_frames)),
            rgb=torch.from_numpy(rgb.reshape(-1, 3)).to(self.device).float().div_(255.0),
            depth=torch.from_numpy(depth.reshape(-1)).to(self.device),
            depth_np=depth, rgb_np=rgb, valid=valid, mask=None if mask is None else np.asarray(mask, bool))

    def _sample(self, valid: np.ndarray, n: int) -> np.ndarray:
        return valid[self.rng.integers(0, len(valid), size=n)]

    def _set_map_grad(self, on: bool) -> None:
        for p in self.model.parameters():
            p.requires_grad_(on)

    # ------------------------------------------------------------------ tracking
    def predict_pose(self) -> np.ndarray:
        """The next frame's pose predicted by the constant-velocity model (before it is tracked)."""
        return self._initial_guess()

    def _initial_guess(self, cur: Optional[_Current] = None) -> np.ndarray:
        """The current frame's initial pose: constant velocity, refined by ICP against the previous
        frame's depth (tracking.icp_init) where that converges near it."""
        p1 = self.poses[-1]
        rel = np.eye(4)  # previous camera <- current camera
        if len(self.poses) >= 2:
            rel = inv_np(self.poses[-2]) @ p1
        self.last_icp = None
        if self.cfg.tracking.icp_init and cur is not None and self._prev_depth is not None:
            res = icp_depth(self._prev_depth, self._icp_depth(cur), (self.intr.fx, self.intr.fy, self.intr.cx, self.intr.cy),
                            init=rel, factors=ICP_FACTORS, iters=ICP_ITERS, max_dist=ICP_MAX_DIST,
                            min_fraction=ICP_MIN_FRACTION, max_points=ICP_MAX_POINTS)
            self.last_icp = res
            if res.ok and self._plausible(res.T, rel, "ICP", cur.idx):
                rel = res.T
        return orthonormalize(p1 @ rel)

    @staticmethod
    def _off_velocity(cand: np.ndarray, rel: np.ndarray) -> float:
        """Distance (m) between the translations of an initial-guess step ``cand`` (previous camera
        <- current) and the constant-velocity step ``rel``."""
        return float(np.linalg.norm(cand[:3, 3] - rel[:3, 3]))

    def _plausible(self, cand: np.ndarray, rel: np.ndarray, source: str, idx: int) -> bool:
        """Whether an initial-guess step ``cand`` lies within ``MAX_JUMP`` of the
        constant-velocity step ``rel``; a rejected one is logged as a ``guess_rejected`` event
        (tracking_events.json)."""
        off = self._off_velocity(cand, rel)
        if off <= MAX_JUMP:
            return True
        self._guess_rejected(idx, f"{source} step {off:.3f} m from constant velocity > {MAX_JUMP} m")
        return False

    def _guess_rejected(self, idx: int, detail: str) -> None:
        """Log an initial guess that was not used (a ``guess_rejected`` event, tracking_events.json)."""
        self.events.append({"frame": int(idx), "kind": "guess_rejected", "detail": detail})
        log.info("frame %d: %s", idx, detail)

    def _pose_of(self, i: int) -> np.ndarray:
        """Frame ``i``'s pose as the trajectory has it (relative to its keyframe, which bundle
        adjustment refines)."""
        r = self.rel[i]
        return self.poses[i] if r is None else self.poses[self.kf_of[i]] @ r

    def _edges(self, cur: _Current, margin: int) -> np.ndarray:
        """Depth-edge pixels of the current frame within ``margin`` px (cached per margin).

        A step counts as an edge when it exceeds 5 % of the depth at a 540 px focal length (about
        0.1 degrees per pixel; only surfaces seen at more than ~88 degrees step that much), scaled
        with the pixel's angular size so that wide, low-resolution cameras do not see every
        oblique wall as an edge."""
        cache = cur.extra.setdefault("edges", {})
        if margin not in cache:
            cache[margin] = depth_edges(cur.depth_np, max(0.05, 27.0 / float(self.intr.fx)), margin)
        return cache[margin]

    def _without_edges(self, cur: _Current, pixels: np.ndarray, margin: int) -> np.ndarray:
        """``pixels`` (flat indices) without depth-edge pixels, unless that leaves fewer than
        MIN_PIXELS (then all of them)."""
        if margin <= 0 or len(pixels) == 0:
            return pixels
        sub = pixels[~self._edges(cur, margin).reshape(-1)[pixels]]
        return sub if len(sub) >= MIN_PIXELS else pixels

    @staticmethod
    def _masked_depth(cur: _Current) -> np.ndarray:
        return cur.depth_np if cur.mask is None else np.where(cur.mask, cur.depth_np, 0).astype(np.float32)

    def _icp_depth(self, cur: _Current) -> np.ndarray:
        """The depth ICP aligns: static pixels, without depth edges (EDGE_MARGIN)."""
        return np.where(self._edges(cur, EDGE_MARGIN), 0, self._masked_depth(cur)).astype(np.float32)

    def track(self, frame, mask: Optional[np.ndarray] = None) -> TrackResult:
        t0 = time.perf_counter()
        cur = self._prepare(frame, mask)
        self._cur = cur
        if self.n_frames == 0:
            gt = getattr(frame, "pose_c2w", None)
            pose = np.array(gt, np.float64) if gt is not None else np.eye(4)
            if self.model is None:
                b = self.bounds if self.bounds is not None else auto_bounds(frame, self.intr, pose, AUTO_MARGIN)
                self._build_model(b)
            if self.cfg.tracking.backend:
                i = self.intr
                self.backend = Backend((i.fx, i.fy, i.cx, i.cy, self.W, self.H), self.cfg.backend, first_pose=pose)
                self._backend_track(frame, cur)
            return self._finish_track(cur, pose, 0.0, 0, False, t0)
        tc = self.cfg.tracking
        iters = int(tc.iters)
        if self.backend is not None:
            out = self._backend_track(frame, cur)
            if not out.lost:
                return self._finish_track(cur, out.pose_c2w, float("nan"), 0, False, t0)
            # lost: dense tracking against the neural map from the constant-velocity pose (if it runs)
            self._event(cur.idx, "lost", out.reason + ("; dense tracking from constant velocity" if iters > 0 else ""))
            init = out.pose_c2w
        else:
            init = self._initial_guess(cur)
        tvalid = self._without_edges(cur, cur.valid, EDGE_MARGIN)
        if len(tvalid) < MIN_PIXELS or iters <= 0:
            reason = f"only {len(tvalid)} usable pixels" if iters > 0 else ""
            if reason:
                self._event(cur.idx, "skipped", reason)
            return self._finish_track(cur, init, float("nan"), 0, bool(reason), t0, reason)
        R, S = tc.n_rays, self.cfg.map.SAMPLES_FREE + self.cfg.map.samples_surface
        if RESAMPLE_RAYS:
            idx = torch.from_numpy(self._sample(tvalid, iters * R)).to(self.device)
        else:
            idx = torch.from_numpy(np.tile(self._sample(tvalid, R), iters)).to(self.device)
        dirs_c = self.dirs[idx].view(iters, R, 3)
        rgb_t = cur.rgb[idx].view(iters, R, 3)
        d_t = cur.depth[idx]
        z_all = sample_depths(d_t, self.cfg.map, self.tgen).view(iters, R, S)
        d_t = d_t.view(iters, R)
        T0 = self._t(init)
        xi = torch.zeros(6, device=self.device, requires_grad=True)
        opt = torch.optim.Adam([xi], lr=tc.lr)
        best_loss, best_xi = float("inf"), torch.zeros(6, device=self.device)
        self._set_map_grad(False)
        bad = ""
        try:
            for it in range(iters):
                T = T0 @ se3_exp(xi)
                o = T[:3, 3].unsqueeze(0)
                d = dirs_c[it] @ T[:3, :3].T
                out = render_rays(self.model, o, d, z_all[it])
                loss = ray_losses(out, z_all[it], rgb_t[it], d_t[it], self.cfg.map).total
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
            self._set_map_grad(True)
        pose = init @ se3_exp(best_xi.double().cpu()).numpy() if self.device.type != "cpu" else \
            init @ se3_exp(best_xi.double()).numpy()
        jump = float(np.linalg.norm(pose[:3, 3] - init[:3, 3]))
        if not bad and (not np.all(np.isfinite(pose)) or best_loss == float("inf")):
            bad = "non-finite pose"
        if not bad and jump > MAX_JUMP:
            bad = f"jump of {jump:.3f} m > {MAX_JUMP} m"
        if bad:
            self._event(cur.idx, "diverged", bad)
            return self._finish_track(cur, init, best_loss, iters, True, t0, bad)
        return self._finish_track(cur, orthonormalize(pose), best_loss, iters, False, t0)

    def _backend_track(self, frame, cur: _Current):
        """The backend's pose of the current frame (static pixels; the depth before the data layer's
        depth cut, where the frame has it, as keypoints beyond it still fix the pose).  A keyframe it
        finds due is inserted by map(), with the frame's final static mask."""
        full = getattr(frame, "depth_full", None)
        depth = cur.depth_np if full is None else np.where(np.isfinite(full), full, 0).astype(np.float32)
        return self.backend.track(cur.idx, cur.rgb_np, depth, cur.mask, defer=True)

    def forget_landmarks(self, frame_id: int, instance_ids) -> int:
        """Remove the backend landmarks that frame ``frame_id``'s keyframe made on ``instance_ids``
        (found to move since); 0 without the backend."""
        return 0 if self.backend is None else self.backend.forget(frame_id, instance_ids)

    def _sync_backend_poses(self) -> None:
        """Every tracked frame's and keyframe's pose from the backend's bundle-adjusted trajectory."""
        traj = self.backend.trajectory()
        for i in range(min(len(traj), len(self.poses))):
            self.poses[i] = traj[i].copy()
        for k in self.keyframes:
            if k.frame_id < len(traj):
                k.pose_c2w = traj[k.frame_id].copy()

    def _event(self, idx: int, kind: str, detail: str) -> None:
        self.events.append({"frame": int(idx), "kind": kind, "detail": detail})
        log.warning("frame %d: tracking %s (%s); using the constant-velocity pose", idx, kind, detail)

    def retrack(self, frame, mask: Optional[np.ndarray] = None) -> TrackResult:
        """Track the last tracked frame again (e.g. with a corrected static mask), replacing its
        pose; must come between track() and map() of that frame."""
        cur = self._cur
        if cur is None or cur.idx != self.n_frames - 1 or cur.idx == 0 or self._undo is None:
            raise DynslamError("SLAM.retrack() must follow track() of the same frame (not the first)")
        if self.backend is not None:  # the backend re-tracks on the keypoints still static; the mask reaches map()
            t0 = time.perf_counter()
            pose = None if mask is None else self.backend.retrack(np.asarray(mask, bool))
            if pose is not None:
                self.poses[-1] = orthonormalize(pose)
            return TrackResult(self.poses[-1].copy(), float("nan"), 0, False, (time.perf_counter() - t0) * 1000,
                               "backend re-tracked" if pose is not None else "backend pose kept")
        for lst in (self.poses, self.timestamps, self.kf_of, self.rel):
            lst.pop()
        self._prev_depth = self._undo[0]
        return self.track(frame, mask)

    def _finish_track(self, cur, pose, loss, iters, diverged, t0, reason="") -> TrackResult:
        ke = self.cfg.mapping.keyframe_every
        self._undo = (self._prev_depth,)
        if self.backend is not None and cur.idx > 0:  # a lost frame's pose came from dense tracking
            self.backend.correct_last(pose)
        if self.backend is None:
            self._prev_depth = self._icp_depth(cur) if self.cfg.tracking.icp_init else None
        self.poses.append(np.array(pose, np.float64))
        self.timestamps.append(cur.timestamp)
        kf_id = (cur.idx // ke) * ke
        self.kf_of.append(kf_id)
        if kf_id < cur.idx and self.backend is None:
            self.rel.append(inv_np(self.poses[kf_id]) @ self.poses[cur.idx])
        else:
            self.rel.append(None)
        return TrackResult(self.poses[-1].copy(), float(loss), int(iters), bool(diverged),
                           (time.perf_counter() - t0) * 1000, reason)

    # ------------------------------------------------------------------ mapping
    def map(self, frame, mask: Optional[np.ndarray] = None, instance_ids: Optional[np.ndarray] = None) -> Optional[MapResult]:
        """Bundle adjustment when due, then keyframe insertion when due, for the last tracked frame."""
        cur = self._cur
        if cur is None or cur.idx != self.n_frames - 1:
            raise DynslamError("SLAM.map() must follow track() of the same frame")
        if mask is not None and (cur.mask is None or not np.array_equal(np.asarray(mask, bool), cur.mask)):
            cur.valid = valid_pixels(cur.depth_np, mask, self.cfg.tracking.ignore_border)
            cur.mask = np.asarray(mask, bool)
            if self.cfg.tracking.icp_init and self.backend is None:  # the next frame's ICP aligns to the static pixels
                self._prev_depth = self._icp_depth(cur)
        mc = self.cfg.mapping
        t0 = time.perf_counter()
        self.backend_keyframe = False
        if self.backend is not None:  # the keyframe the backend found due, with the final static mask
            self.backend_keyframe, _, refined = self.backend.commit(cur.mask, instance_ids)
            if self.backend_keyframe:
                self._sync_backend_poses()
                self.poses[cur.idx] = refined
        ba = False
        iters, loss = 0, float("nan")
        if cur.idx == 0:
            if mc.first_iters > 0:
                loss = self._optimize(cur, mc.first_iters, FIRST_RAYS, first=True)
                iters, ba = mc.first_iters, True
        elif mc.every > 0 and cur.idx % mc.every == 0 and mc.iters > 0:
            loss = self._optimize(cur, mc.iters, mc.n_rays, first=False)
            iters, ba = mc.iters, True
        kf = False
        if cur.idx % mc.keyframe_every == 0:
            self._add_keyframe(cur, frame, instance_ids)
            kf = True
        if not ba and not kf and not self.backend_keyframe:
            return None
        return MapResult(kf, ba, iters, float(loss), (time.perf_counter() - t0) * 1000)

    def _add_keyframe(self, cur: _Current, frame, instance_ids) -> None:
        cand = self._without_edges(cur, valid_pixels(cur.depth_np, None, self.cfg.tracking.ignore_border),
                                   EDGE_MARGIN)
        n = max(1, int(round(self.cfg.mapping.keyframe_ray_fraction * self.H * self.W)))
        n = min(n, len(cand))
        sel = np.sort(self.rng.choice(cand, size=n, replace=False)) if n > 0 else np.zeros(0, np.int64)
        uv = self._uv[sel]
        if instance_ids is not None:
            ids = np.asarray(instance_ids).reshape(-1)[sel].astype(np.int32)
        else:
            ids = np.full(len(sel), -1, np.int32)
        usable = np.ones(len(sel), bool) if cur.mask is None else cur.mask.reshape(-1)[sel].copy()
        kf = Keyframe(cur.idx, cur.timestamp, uv, cur.rgb_np.reshape(-1, 3)[sel].copy(),
                      cur.depth_np.reshape(-1)[sel].copy(), ids, usable, self.poses[cur.idx].copy(),
                      subsample_depth(self._masked_depth(cur)),  # what the map was taught: static pixels
                      depth_raw_small=subsample_depth(cur.depth_np))
        self.keyframes.append(kf)
        self._kf_cache = None

    def _kf_tensors(self):
        if self._kf_cache is None or self._kf_cache["n"] != len(self.keyframes):
            if not self.keyframes:
                return None
            uv = np.concatenate([k.pixels for k in self.keyframes])
            flat = torch.from_numpy((uv[:, 1].astype(np.int64) * self.W + uv[:, 0])).to(self.device)
            self._kf_cache = {
                "n": len(self.keyframes),
                "dirs": self.dirs[flat],
                "rgb": self._t(np.concatenate([k.rgb for k in self.keyframes])) / 255.0,
                "depth": self._t(np.concatenate([k.depth for k in self.keyframes])),
                "owner": torch.from_numpy(np.concatenate([np.full(len(k), i) for i, k in enumerate(self.keyframes)]))
                .to(self.device),
            }
        return self._kf_cache

    def ba_ray_indices(self, cur: _Current, iters: int, n_rays: int, use_keyframes: bool = True):
        """Rays for ``iters`` BA iterations: indices into the concatenated keyframe rays (usable
        ones only) and flat pixel indices of the current frame (its valid, unmasked pixels)."""
        n_kf = len(self.keyframes) if use_keyframes else 0
        usable = np.flatnonzero(np.concatenate([k.usable for k in self.keyframes])) if n_kf else np.zeros(0, np.int64)
        if len(usable) == 0:
            n_cur, n_kfr = n_rays, 0
        else:
            n_cur = min(n_rays, max(n_rays // (n_kf + 1), MIN_RAYS_CURRENT))
            n_kfr = n_rays - n_cur
        cur_valid = self._without_edges(cur, cur.valid, EDGE_MARGIN)
        if len(cur_valid) == 0:
            n_cur, n_kfr = 0, (n_rays if len(usable) else 0)
        kf_idx = usable[self.rng.integers(0, len(usable), size=iters * n_kfr)] if n_kfr else np.zeros(0, np.int64)
        cur_idx = self._sample(cur_valid, iters * n_cur) if n_cur else np.zeros(0, np.int64)
        return kf_idx, cur_idx

    def _optimize(self, cur: _Current, iters: int, n_rays: int, first: bool) -> float:
        """Joint optimisation of the map and (unless ``first``) keyframe + current poses."""
        mc, mp = self.cfg.mapping, self.cfg.map
        kf = None if first else self._kf_tensors()
        n_kf = 0 if kf is None else kf["n"]
        kf_idx_np, cur_idx_np = self.ba_ray_indices(cur, iters, n_rays, use_keyframes=n_kf > 0)
        n_kfr, n_cur = len(kf_idx_np) // iters, len(cur_idx_np) // iters
        if n_cur + n_kfr == 0:
            return float("nan")
        # poses: keyframes (first fixed) + current frame
        kf_poses = [k.pose_c2w for k in self.keyframes] if n_kf else []
        base = np.stack(kf_poses + [self.poses[cur.idx]]) if not first else self.poses[cur.idx][None]
        base_t = self._t(base)
        n_p = base.shape[0]
        opt_mask = torch.ones(n_p, 1, device=self.device)
        if not first:
            opt_mask[0] = 0  # the first keyframe's pose stays fixed
        lr_pose = float(mc.lr_pose)
        optimise_poses = (not first) and bool(opt_mask.sum() > 0) and lr_pose > 0 and self.backend is None
        xi = torch.zeros(n_p, 6, device=self.device, requires_grad=optimise_poses)
        pose_opt = torch.optim.Adam([xi], lr=lr_pose) if optimise_poses else None
        S = mp.SAMPLES_FREE + mp.samples_surface
        # sample all iterations' rays up front
        cur_idx = torch.from_numpy(cur_idx_np).to(self.device) if n_cur else None
        kf_idx = torch.from_numpy(kf_idx_np).to(self.device) if n_kfr else None
        parts_dirs, parts_rgb, parts_d, parts_owner = [], [], [], []
        if n_kfr:
            parts_dirs.append(kf["dirs"][kf_idx].view(iters, n_kfr, 3))
            parts_rgb.append(kf["rgb"][kf_idx].view(iters, n_kfr, 3))
            parts_d.append(kf["depth"][kf_idx].view(iters, n_kfr))
            parts_owner.append(kf["owner"][kf_idx].view(iters, n_kfr))
        if n_cur:
            parts_dirs.append(self.dirs[cur_idx].view(iters, n_cur, 3))
            parts_rgb.append(cur.rgb[cur_idx].view(iters, n_cur, 3))
            parts_d.append(cur.depth[cur_idx].view(iters, n_cur))
            parts_owner.append(torch.full((iters, n_cur), n_p - 1, device=self.device, dtype=torch.long))
        dirs_a = torch.cat(parts_dirs, 1)
        rgb_a = torch.cat(parts_rgb, 1)
        d_a = torch.cat(parts_d, 1)
        own_a = torch.cat(parts_owner, 1)
        R = dirs_a.shape[1]
        z_a = sample_depths(d_a.reshape(-1), mp, self.tgen).view(iters, R, S)
        b = self.model.bounds
        smooth_box = None
        if mp.W_SMOOTH > 0:
            side = mp.SMOOTH_GRID * mp.SMOOTH_VOXEL
            hi = np.maximum(b[1] - side, b[0])
            smooth_box = self._t(np.stack([b[0], hi]))
        last = float("nan")
        accum = POSE_ACCUM_STEPS
        for it in range(iters):
            if optimise_poses:
                T = base_t @ se3_exp(xi * opt_mask)
            else:
                T = base_t
            own = own_a[it]
            # index_select, not T[own]: its backward adds the rays' pose gradients in a fixed order
            # (indexing's scatter-adds them with atomic adds across threads: not repeatable)
            Ts = T.index_select(0, own)
            o = Ts[:, :3, 3]
            d = (Ts[:, :3, :3] @ dirs_a[it][..., None])[..., 0]
            # the smoothness cube's grid features come from the rays' grid call (one table gradient)
            spts = None if smooth_box is None else smoothness_points(smooth_box, mp, self.tgen)
            out = render_rays(self.model, o, d, z_a[it], grid_extra=spts)
            loss = ray_losses(out, z_a[it], rgb_a[it], d_a[it], mp).total
            if spts is not None:
                loss = loss + mp.W_SMOOTH * smoothness_tv(out["grid_extra"], mp)
            self.map_opt.zero_grad(set_to_none=True)
            loss.backward()
            self.map_opt.step()
            if pose_opt is not None and ((it + 1) % accum == 0 or it == iters - 1):
                pose_opt.step()  # on the pose gradients summed since the last pose step
                pose_opt.zero_grad(set_to_none=True)
            last = float(loss.detach())
        if not np.isfinite(last):
            self._event(cur.idx, "mapping-nonfinite", "bundle adjustment loss is not finite")
        if optimise_poses:
            with torch.no_grad():
                new = (base_t.double() @ se3_exp((xi * opt_mask).double())).cpu().numpy()
            if np.all(np.isfinite(new)):
                for i, k in enumerate(self.keyframes[:n_kf]):
                    k.pose_c2w = orthonormalize(new[i])
                    self.poses[k.frame_id] = k.pose_c2w.copy()
                self.poses[cur.idx] = orthonormalize(new[-1])
        return last

    def finish(self) -> Optional[MapResult]:
        """After the last frame: mapping.final_iters more bundle adjustment iterations over all
        keyframes and the last tracked frame (the periodic BA's code path); None when off."""
        iters = int(self.cfg.mapping.final_iters)
        cur = self._cur
        if self.backend is not None:
            self._sync_backend_poses()
        if iters <= 0 or cur is None or cur.idx != self.n_frames - 1 or cur.idx == 0 or not self.keyframes:
            return None
        t0 = time.perf_counter()
        loss = self._optimize(cur, iters, self.cfg.mapping.n_rays, first=False)
        return MapResult(False, True, iters, float(loss), (time.perf_counter() - t0) * 1000)

    def process(self, frame, mask=None, instance_ids=None) -> FrameResult:
        t0 = time.perf_counter()
        tr = self.track(frame, mask)
        mr = self.map(frame, mask, instance_ids)
        idx = self.n_frames - 1
        return FrameResult(idx, self.timestamps[idx], self.poses[idx].copy(), tr, mr,
                           (time.perf_counter() - t0) * 1000)

    # ------------------------------------------------------------------ outputs
    def trajectory(self) -> np.ndarray:
        """(N, 4, 4) c2w; non-keyframes re-expressed relative to their refined keyframe (the
        backend's bundle-adjusted trajectory when it tracks)."""
        if self.backend is not None:
            return self.backend.trajectory()[:self.n_frames].copy()
        out = np.zeros((self.n_frames, 4, 4))
        for i in range(self.n_frames):
            out[i] = self._pose_of(i)
        return out

    @torch.no_grad()
    def render(self, pose_c2w: np.ndarray, scale: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
        """Depth (h×w, m; 0 = no surface) and colour (h×w×3 uint8) rendered at ``scale`` resolution
        without depth guidance: coarse samples over [near, far], then fine samples around the first
        surface crossing."""
        if self.model is None:
            raise DynslamError("render() needs a map: process a frame first")
        mp = self.cfg.map
        h, w = max(1, int(round(self.H * scale))), max(1, int(round(self.W * scale)))
        vv, uu = np.mgrid[0:h, 0:w]
        sx, sy = self.W / w, self.H / h
        u = (uu.ravel() + 0.5) * sx - 0.5
        v = (vv.ravel() + 0.5) * sy - 0.5
        dirs = self._t(pixel_dirs(u, v, self.intr.fx, self.intr.fy, self.intr.cx, self.intr.cy))
        T = self._t(pose_c2w)
        d = dirs @ T[:3, :3].T
        o = T[:3, 3].unsqueeze(0)
        depth = torch.zeros(len(d), device=self.device)
        rgb = torch.zeros(len(d), 3, device=self.device)
        nc, nf = RENDER_COARSE, RENDER_FINE
        zc = mp.near + (torch.arange(nc, device=self.device, dtype=torch.float32) + 0.5) / nc * (mp.far - mp.near)
        tr = self.model.truncation
        chunk = max(1, 65536 // nc)
        for i in range(0, len(d), chunk):
            dd = d[i:i + chunk]
            r = len(dd)
            pts = o[:, None, :] + dd[:, None, :] * zc[None, :, None]
            s = self.model(pts.reshape(-1, 3), color=False)[0].view(r, nc)
            cross = (s[:, :-1] > 0) & (s[:, 1:] <= 0)
            has = cross.any(1)
            j = cross.float().argmax(1)
            s0 = s.gather(1, j[:, None])[:, 0]
            s1 = s.gather(1, (j + 1)[:, None])[:, 0]
            z0 = zc[j]
            z1 = zc[j + 1]
            zs = z0 + (z1 - z0) * s0 / (s0 - s1).clamp_min(1e-6)
            k = torch.arange(nf, device=self.device, dtype=torch.float32)
            zf = (zs - tr)[:, None] + (k + 0.5) / nf * 2 * tr
            zf = zf.clamp_min(mp.near)
            out = render_rays(self.model, o, dd, zf)
            depth[i:i + chunk] = torch.where(has, out["depth"], torch.zeros_like(zs))
            rgb[i:i + chunk] = out["rgb"] * has[:, None]
        return (depth.view(h, w).cpu().numpy(),
                (rgb.view(h, w, 3).cpu().numpy() * 255).clip(0, 255).astype(np.uint8))

    def observed_points(self, max_points: int = 2_000_000) -> np.ndarray:
        pts = [k.world_points(self.intr) for k in self.keyframes]
        if not pts:
            return np.zeros((0, 3))
        p = np.concatenate(pts)
        if len(p) > max_points:
            p = p[np.random.default_rng(0).choice(len(p), max_points, replace=False)]
        return p

    def extract_mesh(self, voxel: float):
        from dynslam_cli.map.mesh import extract_mesh

        if self.model is None:
            raise DynslamError("extract_mesh() needs a map: process a frame first")
        return extract_mesh(self.model, self.observed_points(), voxel, self.device)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        return {
            "version": 1,
            "bounds": None if self.bounds is None else self.bounds.copy(),
            "model": None if self.model is None else {k: v.detach().cpu().clone() for k, v in self.model.state_dict().items()},
            "map_opt": None if self.map_opt is None else self.map_opt.state_dict(),
            "keyframes": [k.to_dict() for k in self.keyframes],
            "poses": np.array(self.poses).reshape(-1, 4, 4),
            "rel": [None if r is None else r.copy() for r in self.rel],
            "kf_of": list(self.kf_of),
            "timestamps": list(self.timestamps),
            "events": list(self.events),
            "rng": self.rng.bit_generator.state,
            "tgen": self.tgen.get_state().cpu(),
            "prev_depth": None if self._prev_depth is None else self._prev_depth.copy(),
            "backend": None if self.backend is None else self.backend.state_dict(),
        }

    def load_state_dict(self, d: dict) -> None:
        if d.get("bounds") is not None:
            self._build_model(np.asarray(d["bounds"]))
            self.model.load_state_dict(d["model"])
            if d.get("map_opt") is not None:
                self.map_opt.load_state_dict(d["map_opt"])
        self.keyframes = [Keyframe.from_dict(k) for k in d["keyframes"]]
        self.poses = [np.array(p, np.float64) for p in d["poses"]]
        self.rel = [None if r is None else np.array(r) for r in d["rel"]]
        self.kf_of = list(d["kf_of"])
        self.timestamps = list(d["timestamps"])
        self.events = list(d["events"])
        self.rng.bit_generator.state = d["rng"]
        self.tgen.set_state(d["tgen"])
        self._cur = None
        self._kf_cache = None
        pd = d.get("prev_depth")
        self._prev_depth = None if pd is None else np.asarray(pd, np.float32)
        self.backend = None
        if d.get("backend") is not None:
            i = self.intr
            self.backend = Backend((i.fx, i.fy, i.cx, i.cy, self.W, self.H), self.cfg.backend)
            self.backend.load_state_dict(d["backend"])
