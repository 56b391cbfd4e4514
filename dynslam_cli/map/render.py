"""Ray sampling and volume rendering of the SDF map (Co-SLAM's weights).

Depth-guided sampling: rays with a depth measurement ``d`` get ``samples_free`` stratified samples
in ``[near, d - surface_range]`` and ``samples_surface`` stratified samples in
``d ± surface_range``; rays without depth get as many (``samples_free + samples_surface``)
stratified samples in ``[near, far]``, so the tensors stay rectangular.

Weights exactly as Co-SLAM computes them: ``w = sigmoid(s / tr) * sigmoid(-s / tr)`` where ``s`` is
the decoder's raw SDF, which is in truncation units (Co-SLAM's ``raw2outputs`` passes ``raw[..., 3]``
to ``sdf2weights``, which divides by ``trunc``).  In metres that is ``sigma(s_m / tr^2)``: a sharp
peak at the surface, so free-space samples (s = 1) get ~0 weight and the rendered depth is unbiased.
Weights are kept only up to one truncation behind the first surface crossing and normalised along
the ray.  Colour and depth are the weighted means.
"""

from __future__ import annotations

import torch

from dynslam_cli.map.config import MapConfig


def n_samples(cfg: MapConfig) -> int:
    return cfg.SAMPLES_FREE + cfg.samples_surface


def sample_depths(depth: torch.Tensor, cfg: MapConfig, generator: torch.Generator | None = None,
                  perturb: bool = True) -> torch.Tensor:
    """Sorted sample distances (R, S) for rays with measured depth (R,) (0 = missing)."""
    r = depth.shape[0]
    nf, ns = cfg.SAMPLES_FREE, cfg.samples_surface
    s = nf + ns
    dev = depth.device
    if perturb:
        u = torch.rand(r, s, device=dev, generator=generator)
    else:
        u = torch.full((r, s), 0.5, device=dev)
    has = depth > 0
    d = torch.where(has, depth, torch.ones_like(depth))
    lo_band = (d - cfg.surface_range).clamp_min(cfg.near)
    hi_band = d + cfg.surface_range
    # band: stratified in [lo_band, hi_band]
    kb = torch.arange(ns, device=dev, dtype=torch.float32)
    band = lo_band[:, None] + (kb + u[:, nf:]) / ns * (hi_band - lo_band)[:, None]
    if nf > 0:
        kf = torch.arange(nf, device=dev, dtype=torch.float32)
        hi_free = torch.maximum(lo_band, torch.full_like(lo_band, cfg.near))
        free = cfg.near + (kf + u[:, :nf]) / nf * (hi_free - cfg.near)[:, None]
        z = torch.cat([free, band], dim=1)
    else:
        z = band
    # rays without depth: stratified over [near, far]
    km = torch.arange(s, device=dev, dtype=torch.float32)
    zm = cfg.near + (km + u) / s * (cfg.far - cfg.near)
    return torch.where(has[:, None], z, zm)


def sdf_weights(sdf: torch.Tensor, z: torch.Tensor, truncation: float) -> torch.Tensor:
    """Co-SLAM rendering weights from SDF (R, S) in truncation units at sorted distances z."""
    w = torch.sigmoid(sdf / truncation) * torch.sigmoid(-sdf / truncation)
    with torch.no_grad():
        sign_change = (sdf[:, :-1] > 0) & (sdf[:, 1:] <= 0)  # first front-to-back crossing
        has = sign_change.any(dim=1)
        first = sign_change.float().argmax(dim=1)
        zmin = torch.gather(z, 1, first[:, None])[:, 0]
        zmin = torch.where(has, zmin, z[:, -1])
        keep = (z < (zmin + truncation)[:, None]).to(w.dtype)
    w = w * keep
    return w / (w.sum(dim=1, keepdim=True) + 1e-8)


def render_rays(model, rays_o: torch.Tensor, rays_d: torch.Tensor, z: torch.Tensor, color: bool = True,
                grid_extra: torch.Tensor | None = None):
    """Query the map along rays. rays_o (R, 3) or (1, 3), rays_d (R, 3), z (R, S).

    Returns dict: sdf (R, S), rgb (R, 3) or None, depth (R,), weights (R, S), and grid_extra: the
    grid features of the world points ``grid_extra`` (M, 3) from the same grid call (or None)."""
    r, s = z.shape
    pts = rays_o[:, None, :] + rays_d[:, None, :] * z[..., None]
    sdf, rgb, extra = model.query(pts.reshape(-1, 3), color=color, grid_extra=grid_extra)
    sdf = sdf.view(r, s)
    w = sdf_weights(sdf, z, model.truncation)
    out = {"sdf": sdf, "weights": w, "depth": (w * z).sum(dim=1), "rgb": None, "grid_extra": extra}
    if color:
        out["rgb"] = (w[..., None] * rgb.view(r, s, 3)).sum(dim=1)
    return out
