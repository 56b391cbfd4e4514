"""Outputs of the neural map: views rendered without depth guidance (the dynamic check), the
keyframes' observed points and the mesh."""

from __future__ import annotations

import numpy as np
import torch

from dynslam_cli.geometry.camera import pixel_dirs
from dynslam_cli.map.render import render_rays

# render_view() without depth: coarse samples over [near, far], then fine samples around the first surface crossing
# (32 / 8 at check resolution; Co-SLAM renders 64 / 16).
RENDER_COARSE = 32
RENDER_FINE = 8
# The coarse samples are evaluated this many at a time, near to far, and only on the rays without a crossing yet: the
# same first crossing as evaluating all of them, at about two thirds of the cost (most rays cross by mid-range).
RENDER_BLOCK = 8


def _first_crossing(model, o: torch.Tensor, d: torch.Tensor, zc: torch.Tensor):
    """The first front-to-back SDF crossing of each ray ``o + z d`` over the coarse distances ``zc``:
    (index j of the sample before it, SDF at j and j + 1, whether the ray has one); j = 0 without.
    Samples are evaluated in blocks of :data:`RENDER_BLOCK`, near to far, on the rays still without
    a crossing; the result equals evaluating every sample of every ray."""
    r, nc = len(d), len(zc)
    dev = d.device
    j = torch.zeros(r, dtype=torch.long, device=dev)
    s0 = torch.zeros(r, device=dev)
    s1 = torch.zeros(r, device=dev)
    has = torch.zeros(r, dtype=torch.bool, device=dev)
    todo = torch.arange(r, device=dev)
    prev = None  # SDF of the todo rays at the sample before the block
    for a in range(0, nc, RENDER_BLOCK):
        if len(todo) == 0:
            break
        zb = zc[a:a + RENDER_BLOCK]
        pts = o[:, None, :] + d[todo][:, None, :] * zb[None, :, None]
        s = model(pts.reshape(-1, 3), color=False)[0].view(len(todo), len(zb))
        first = a
        if prev is not None:
            s = torch.cat([prev[:, None], s], 1)
            first = a - 1
        cross = (s[:, :-1] > 0) & (s[:, 1:] <= 0)
        hit = cross.any(1)
        k = cross.float().argmax(1)
        rows, sh, kh = todo[hit], s[hit], k[hit][:, None]
        j[rows] = first + kh[:, 0]
        s0[rows] = sh.gather(1, kh)[:, 0]
        s1[rows] = sh.gather(1, kh + 1)[:, 0]
        has[rows] = True
        todo = todo[~hit]
        prev = s[~hit, -1]
    return j, s0, s1, has


@torch.no_grad()
def render_view(model, map_cfg, intr, pose_c2w: np.ndarray, scale: float, device) -> tuple[np.ndarray, np.ndarray]:
    """Depth (h×w, m; 0 = no surface) and colour (h×w×3 uint8) of ``model`` seen from ``pose_c2w``
    by the camera ``intr`` at ``scale`` resolution, without depth guidance: coarse samples over
    [near, far], then fine samples around the first surface crossing."""
    mp = map_cfg
    H, W = int(intr.height), int(intr.width)
    h, w = max(1, int(round(H * scale))), max(1, int(round(W * scale)))
    vv, uu = np.mgrid[0:h, 0:w]
    sx, sy = W / w, H / h
    u = (uu.ravel() + 0.5) * sx - 0.5
    v = (vv.ravel() + 0.5) * sy - 0.5
    dirs = torch.as_tensor(pixel_dirs(u, v, intr.fx, intr.fy, intr.cx, intr.cy), dtype=torch.float32).to(device)
    T = torch.as_tensor(np.asarray(pose_c2w), dtype=torch.float32).to(device)
    d = dirs @ T[:3, :3].T
    o = T[:3, 3].unsqueeze(0)
    depth = torch.zeros(len(d), device=device)
    rgb = torch.zeros(len(d), 3, device=device)
    nc, nf = RENDER_COARSE, RENDER_FINE
    zc = mp.near + (torch.arange(nc, device=device, dtype=torch.float32) + 0.5) / nc * (mp.far - mp.near)
    tr = model.truncation
    chunk = max(1, 65536 // RENDER_BLOCK)  # rays per pass: at most 64k points per model call
    for i in range(0, len(d), chunk):
        dd = d[i:i + chunk]
        j, s0, s1, has = _first_crossing(model, o, dd, zc)
        z0 = zc[j]
        z1 = zc[j + 1]
        zs = z0 + (z1 - z0) * s0 / (s0 - s1).clamp_min(1e-6)
        k = torch.arange(nf, device=device, dtype=torch.float32)
        zf = (zs - tr)[:, None] + (k + 0.5) / nf * 2 * tr
        zf = zf.clamp_min(mp.near)
        out = render_rays(model, o, dd, zf)
        depth[i:i + chunk] = torch.where(has, out["depth"], torch.zeros_like(zs))
        rgb[i:i + chunk] = out["rgb"] * has[:, None]
    return (depth.view(h, w).cpu().numpy(),
            (rgb.view(h, w, 3).cpu().numpy() * 255).clip(0, 255).astype(np.uint8))


def observed_points(keyframes, intr, max_points: int = 2_000_000) -> np.ndarray:
    """The keyframes' stored depth as world points (N×3); a fixed random subset of ``max_points``
    when there are more."""
    pts = [k.world_points(intr) for k in keyframes]
    if not pts:
        return np.zeros((0, 3))
    p = np.concatenate(pts)
    if len(p) > max_points:
        p = p[np.random.default_rng(0).choice(len(p), max_points, replace=False)]
    return p


def extract_mesh(model, keyframes, intr, voxel: float, device):
    """The map's mesh at ``voxel`` size, kept near the keyframes' observed points."""
    from dynslam_cli.map.mesh import extract_mesh as mesh_of

    return mesh_of(model, observed_points(keyframes, intr), voxel, device)
