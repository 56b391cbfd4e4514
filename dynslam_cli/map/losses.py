"""Co-SLAM's losses: colour, depth, SDF (inside the truncation band), free space (in front of it)
and feature smoothness.  Means are over all samples as in Co-SLAM's ``get_sdf_loss``, with its
balancing factors between free-space and SDF samples."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from dynslam_cli.map.config import MapConfig


@dataclass
class LossTerms:
    total: torch.Tensor
    rgb: torch.Tensor
    depth: torch.Tensor
    sdf: torch.Tensor
    free: torch.Tensor


def sdf_band(z: torch.Tensor, target_d: torch.Tensor, truncation: float, dtype=torch.float32):
    """Masks (R, S) as ``dtype`` of the samples z in front of the truncation band around the
    measured depth target_d (R,) and of those inside it, on rays with depth (0 = missing)."""
    td = target_d[:, None]
    valid = (td > 0).to(dtype)
    front = (z < td - truncation).to(dtype) * valid
    back = (z > td + truncation).to(dtype)
    return front, (1 - front) * (1 - back) * valid


def sdf_free_losses(z: torch.Tensor, target_d: torch.Tensor, sdf: torch.Tensor, truncation: float):
    """Free-space and SDF losses; sdf in truncation units; target_d (R,) with 0 = missing."""
    td = target_d[:, None]
    front, band = sdf_band(z, target_d, truncation, sdf.dtype)
    n_front = front.sum()
    n_band = band.sum()
    n_all = (n_front + n_band).clamp_min(1.0)
    fs_weight = 1 - n_front / n_all
    sdf_weight = 1 - n_band / n_all
    numel = sdf.numel()
    free = ((sdf - 1.0) * front).square().sum() / numel * fs_weight
    sdf_l = ((z + sdf * truncation - td) * band).square().sum() / numel * sdf_weight
    return free, sdf_l


def ray_losses(out: dict, z: torch.Tensor, target_rgb: torch.Tensor, target_d: torch.Tensor,
               cfg: MapConfig) -> LossTerms:
    has = target_d > 0
    if out["rgb"] is not None:
        wr = torch.where(has, torch.ones_like(target_d), torch.full_like(target_d, cfg.RGB_MISSING))
        rgb = ((out["rgb"] - target_rgb).square() * wr[:, None]).mean()
    else:
        rgb = torch.zeros((), device=z.device)
    n_has = has.sum().clamp_min(1)
    depth = ((out["depth"] - target_d).square() * has).sum() / n_has
    free, sdf = sdf_free_losses(z, target_d, out["sdf"], cfg.truncation)
    total = cfg.w_rgb * rgb + cfg.w_depth * depth + cfg.w_sdf * sdf + cfg.w_free * free
    return LossTerms(total, rgb, depth, sdf, free)


def smoothness_points(centre_range: torch.Tensor, cfg: MapConfig, generator: torch.Generator | None = None):
    """The smoothness loss's points: a cube of ``smooth_grid``^3 points ``smooth_voxel`` apart whose
    corner is drawn uniformly in the world-space box centre_range (2, 3)."""
    n = cfg.SMOOTH_GRID
    dev = centre_range.device
    lo = centre_range[0] + torch.rand(3, device=dev, generator=generator) * (centre_range[1] - centre_range[0])
    k = torch.arange(n, device=dev, dtype=torch.float32) * cfg.SMOOTH_VOXEL
    gx, gy, gz = torch.meshgrid(k, k, k, indexing="ij")
    return torch.stack([gx, gy, gz], -1).reshape(-1, 3) + lo


def smoothness_tv(features: torch.Tensor, cfg: MapConfig) -> torch.Tensor:
    """Total variation of the grid features (smooth_grid^3, C) of :func:`smoothness_points`."""
    n = cfg.SMOOTH_GRID
    f = features.view(n, n, n, -1)
    tv = ((f[1:, :-1, :-1] - f[:-1, :-1, :-1]).square() + (f[:-1, 1:, :-1] - f[:-1, :-1, :-1]).square()
          + (f[:-1, :-1, 1:] - f[:-1, :-1, :-1]).square())
    return tv.mean()


def smoothness_loss(model, centre_range: torch.Tensor, cfg: MapConfig, generator: torch.Generator | None = None):
    """Total variation of grid features on a small random cube of points (Co-SLAM smoothness).

    centre_range: (2, 3) world-space box where the cube's corner is drawn.  Bundle adjustment
    computes the same from the ray query's grid call (``render_rays(grid_extra=...)``)."""
    return smoothness_tv(model.grid_features(smoothness_points(centre_range, cfg, generator)), cfg)
