"""The neural map's optimisation: the map itself, first-frame mapping, bundle adjustment over rays
of the keyframes and the current frame (and, without the backend, of the keyframe poses), keyframe
insertion with stored rays.

Every ray sampler takes a per-pixel mask (H×W bool, True = usable); the dynamic module passes its
static mask and later refreshes ``keyframes[k].usable``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from dynslam_cli.errors import DynslamError
from dynslam_cli.geometry.camera import backproject
from dynslam_cli.geometry.lie import orthonormalize, se3_exp
from dynslam_cli.map.losses import ray_losses, smoothness_points, smoothness_tv
from dynslam_cli.map.model import NeuralMap
from dynslam_cli.map.render import n_samples, render_rays, sample_depths
from dynslam_cli.slam.keyframes import Keyframe, subsample_depth, valid_pixels
from dynslam_cli.slam.state import EDGE_MARGIN, CurrentFrame, SlamState
from dynslam_cli.utils.adam import Adam

# Margin (m) added around the first frame's points when map.bounds is null.
AUTO_MARGIN = 2.0
# Rays per mapping iteration on the first frame.
FIRST_RAYS = 2048
# At least this many of the BA rays come from the current frame (Co-SLAM min_pixels_cur).
MIN_RAYS_CURRENT = 100
# Bundle adjustment steps the pose optimiser once every N iterations on the gradients summed over them (Co-SLAM
# pose_accum_step); the map steps every iteration.  The first keyframe's pose stays fixed, the current frame's is
# refined with the keyframes' (Co-SLAM optim_cur).
POSE_ACCUM_STEPS = 5


@dataclass
class MapResult:
    keyframe: bool
    ba: bool
    iters: int
    loss: float
    ms: float


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


class Mapper:
    """Builds and trains the neural map of the shared state; inserts keyframes."""

    def __init__(self, state: SlamState):
        self.s = state

    def build_model(self, bounds: np.ndarray) -> None:
        """A fresh neural map over ``bounds`` (initialised from run.seed) and its optimiser."""
        s = self.s
        s.bounds = np.asarray(bounds, np.float64)
        with torch.random.fork_rng(devices=[]):  # initialise from run.seed, leave the global RNGs alone
            torch.random.default_generator.manual_seed(int(s.cfg.run.seed))  # the CPU's: built there
            s.model = NeuralMap(s.cfg.map, s.bounds).to(s.device)
        s.map_opt = Adam(s.model.parameters(), lr=s.cfg.mapping.lr_map, betas=(0.9, 0.99), eps=1e-15,
                         fused=s.device.type in ("cpu", "cuda"))

    def map(self, frame, cur: CurrentFrame, instance_ids: Optional[np.ndarray] = None) -> Optional[MapResult]:
        """The backend's keyframe when due, bundle adjustment when due, then keyframe insertion when
        due, for the tracked frame ``cur``; None when nothing ran."""
        s = self.s
        mc = s.cfg.mapping
        t0 = time.perf_counter()
        backend_keyframe = False
        if s.backend is not None:  # the keyframe the backend found due, with the mask map() was given
            backend_keyframe, _, refined = s.backend.commit(cur.mask, instance_ids)
            if backend_keyframe:
                s.sync_backend_poses()
                s.poses[cur.idx] = refined
        ba = False
        iters, loss = 0, float("nan")
        if cur.idx == 0:
            if mc.first_iters > 0:
                loss = self.optimize(cur, mc.first_iters, FIRST_RAYS, first=True)
                iters, ba = mc.first_iters, True
        elif mc.every > 0 and cur.idx % mc.every == 0 and mc.iters > 0:
            loss = self.optimize(cur, mc.iters, mc.n_rays, first=False)
            iters, ba = mc.iters, True
        kf = False
        if cur.idx % mc.keyframe_every == 0:
            self.add_keyframe(cur, instance_ids)
            kf = True
        if not ba and not kf and not backend_keyframe:
            return None
        return MapResult(kf, ba, iters, float(loss), (time.perf_counter() - t0) * 1000)

    def add_keyframe(self, cur: CurrentFrame, instance_ids) -> Keyframe:
        """Store a fraction (mapping.keyframe_ray_fraction) of ``cur``'s pixels, off depth edges,
        with their instance ids and usable (static) flags, as a keyframe."""
        s = self.s
        cand = cur.without_edges(valid_pixels(cur.depth_np, None, s.cfg.tracking.ignore_border), EDGE_MARGIN,
                                 s.intr.fx)
        n = max(1, int(round(s.cfg.mapping.keyframe_ray_fraction * s.H * s.W)))
        n = min(n, len(cand))
        sel = np.sort(s.rng.choice(cand, size=n, replace=False)) if n > 0 else np.zeros(0, np.int64)
        uv = s.uv[sel]
        if instance_ids is not None:
            ids = np.asarray(instance_ids).reshape(-1)[sel].astype(np.int32)
        else:
            ids = np.full(len(sel), -1, np.int32)
        usable = np.ones(len(sel), bool) if cur.mask is None else cur.mask.reshape(-1)[sel].copy()
        kf = Keyframe(cur.idx, cur.timestamp, uv, cur.rgb_np.reshape(-1, 3)[sel].copy(),
                      cur.depth_np.reshape(-1)[sel].copy(), ids, usable, s.poses[cur.idx].copy(),
                      subsample_depth(cur.masked_depth()),  # what the map was taught: static pixels
                      depth_raw_small=subsample_depth(cur.depth_np))
        s.keyframes.add(kf)
        return kf

    def keyframe_rays(self, idx: np.ndarray) -> Optional[dict]:
        """The keyframes' stored rays ``idx`` (indices into all keyframes' rays in keyframe order, as
        :meth:`ba_ray_indices` draws them) as tensors: camera directions, colours (0-1), depths and
        the keyframe each belongs to; None without keyframes.  Gathered from the keyframes' own
        arrays on each call: nothing is copied for the rays not drawn."""
        s = self.s
        if not s.keyframes:
            return None
        uv, rgb, depth, owner = s.keyframes.gather(idx)
        flat = torch.from_numpy(uv[:, 1] * s.W + uv[:, 0]).to(s.device)
        return {"n": len(s.keyframes), "dirs": s.dirs[flat], "rgb": s.t(rgb) / 255.0, "depth": s.t(depth),
                "owner": torch.from_numpy(owner).to(s.device)}

    def ba_ray_indices(self, cur: CurrentFrame, iters: int, n_rays: int, use_keyframes: bool = True):
        """Rays for ``iters`` BA iterations: indices into the concatenated keyframe rays (usable
        ones only) and flat pixel indices of the current frame (its valid, unmasked pixels)."""
        s = self.s
        n_kf = len(s.keyframes) if use_keyframes else 0
        usable = s.keyframes.usable_rays() if n_kf else np.zeros(0, np.int64)
        if len(usable) == 0:
            n_cur, n_kfr = n_rays, 0
        else:
            n_cur = min(n_rays, max(n_rays // (n_kf + 1), MIN_RAYS_CURRENT))
            n_kfr = n_rays - n_cur
        cur_valid = cur.without_edges(cur.valid, EDGE_MARGIN, s.intr.fx)
        if len(cur_valid) == 0:
            n_cur, n_kfr = 0, (n_rays if len(usable) else 0)
        kf_idx = usable[s.rng.integers(0, len(usable), size=iters * n_kfr)] if n_kfr else np.zeros(0, np.int64)
        cur_idx = s.sample(cur_valid, iters * n_cur) if n_cur else np.zeros(0, np.int64)
        return kf_idx, cur_idx

    def optimize(self, cur: CurrentFrame, iters: int, n_rays: int, first: bool) -> float:
        """Joint optimisation of the map and (unless ``first``, and without the backend) the
        keyframe + current poses; the last iteration's loss."""
        s = self.s
        mc, mp = s.cfg.mapping, s.cfg.map
        n_kf = 0 if first else len(s.keyframes)
        kf_idx_np, cur_idx_np = self.ba_ray_indices(cur, iters, n_rays, use_keyframes=n_kf > 0)
        n_kfr, n_cur = len(kf_idx_np) // iters, len(cur_idx_np) // iters
        if n_cur + n_kfr == 0:
            return float("nan")
        # poses: keyframes (first fixed) + current frame
        kf_poses = [k.pose_c2w for k in s.keyframes] if n_kf else []
        base = np.stack(kf_poses + [s.poses[cur.idx]]) if not first else s.poses[cur.idx][None]
        base_t = s.t(base)
        n_p = base.shape[0]
        opt_mask = torch.ones(n_p, 1, device=s.device)
        if not first:
            opt_mask[0] = 0  # the first keyframe's pose stays fixed
        lr_pose = float(mc.lr_pose)
        optimise_poses = (not first) and bool(opt_mask.sum() > 0) and lr_pose > 0 and s.backend is None
        xi = torch.zeros(n_p, 6, device=s.device, requires_grad=optimise_poses)
        pose_opt = Adam([xi], lr=lr_pose) if optimise_poses else None
        S = n_samples(mp)
        # sample all iterations' rays up front
        cur_idx = torch.from_numpy(cur_idx_np).to(s.device) if n_cur else None
        parts_dirs, parts_rgb, parts_d, parts_owner = [], [], [], []
        if n_kfr:
            kf = self.keyframe_rays(kf_idx_np)
            parts_dirs.append(kf["dirs"].view(iters, n_kfr, 3))
            parts_rgb.append(kf["rgb"].view(iters, n_kfr, 3))
            parts_d.append(kf["depth"].view(iters, n_kfr))
            parts_owner.append(kf["owner"].view(iters, n_kfr))
        if n_cur:
            parts_dirs.append(s.dirs[cur_idx].view(iters, n_cur, 3))
            parts_rgb.append(cur.rgb[cur_idx].view(iters, n_cur, 3))
            parts_d.append(cur.depth[cur_idx].view(iters, n_cur))
            parts_owner.append(torch.full((iters, n_cur), n_p - 1, device=s.device, dtype=torch.long))
        dirs_a = torch.cat(parts_dirs, 1)
        rgb_a = torch.cat(parts_rgb, 1)
        d_a = torch.cat(parts_d, 1)
        own_a = torch.cat(parts_owner, 1)
        R = dirs_a.shape[1]
        z_a = sample_depths(d_a.reshape(-1), mp, s.tgen).view(iters, R, S)
        b = s.model.bounds
        smooth_box = None
        if mp.W_SMOOTH > 0:
            side = mp.SMOOTH_GRID * mp.SMOOTH_VOXEL
            hi = np.maximum(b[1] - side, b[0])
            smooth_box = s.t(np.stack([b[0], hi]))
        last_t = None  # the last iteration's loss, read once after the loop (no device sync per iteration)
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
            spts = None if smooth_box is None else smoothness_points(smooth_box, mp, s.tgen)
            out = render_rays(s.model, o, d, z_a[it], grid_extra=spts)
            loss = ray_losses(out, z_a[it], rgb_a[it], d_a[it], mp).total
            if spts is not None:
                loss = loss + mp.W_SMOOTH * smoothness_tv(out["grid_extra"], mp)
            s.map_opt.zero_grad(set_to_none=True)
            loss.backward()
            s.map_opt.step()
            if pose_opt is not None and ((it + 1) % accum == 0 or it == iters - 1):
                pose_opt.step()  # on the pose gradients summed since the last pose step
                pose_opt.zero_grad(set_to_none=True)
            last_t = loss.detach()
        last = float("nan") if last_t is None else float(last_t)
        if not np.isfinite(last):
            s.event(cur.idx, "mapping-nonfinite", "bundle adjustment loss is not finite")
        if optimise_poses:
            with torch.no_grad():
                new = (base_t.double() @ se3_exp((xi * opt_mask).double())).cpu().numpy()
            if np.all(np.isfinite(new)):
                for i, k in enumerate(s.keyframes[:n_kf]):
                    k.pose_c2w = orthonormalize(new[i])
                    s.poses[k.frame_id] = k.pose_c2w.copy()
                s.poses[cur.idx] = orthonormalize(new[-1])
        return last

    def finish(self) -> Optional[MapResult]:
        """After the last frame: mapping.final_iters more bundle adjustment iterations over all
        keyframes and the last tracked frame (the periodic BA's code path); None when off."""
        s = self.s
        iters = int(s.cfg.mapping.final_iters)
        cur = s.cur
        if s.backend is not None:
            s.sync_backend_poses()
        if iters <= 0 or cur is None or cur.idx != s.n_frames - 1 or cur.idx == 0 or not s.keyframes:
            return None
        t0 = time.perf_counter()
        loss = self.optimize(cur, iters, s.cfg.mapping.n_rays, first=False)
        return MapResult(False, True, iters, float(loss), (time.perf_counter() - t0) * 1000)
