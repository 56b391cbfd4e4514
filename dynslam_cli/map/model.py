"""The neural map f(x) -> (truncated SDF, colour) of Co-SLAM: hash grid + one-blob -> small MLPs.

* coordinates are normalised per axis by the scene bounds to [0, 1];
* SDF decoder: [grid features, one-blob] -> hidden (ReLU) -> (sdf, geo_feat); the SDF is in units
  of the truncation ``tr`` (Co-SLAM's convention: metres = sdf * tr);
* colour decoder: [one-blob, geo_feat] -> hidden (ReLU) -> RGB (sigmoid).
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np
import torch
import torch.nn.functional as F

from dynslam_cli.errors import DynslamError
from dynslam_cli.map.config import MapConfig
from dynslam_cli.map.encoding import OneBlob
from dynslam_cli.map.hashgrid import HashGrid


class _MLP(torch.nn.Module):
    """Linear -> ReLU -> ... -> Linear, written as plain addmm calls."""

    def __init__(self, dims: list[int]):
        super().__init__()
        self.layers = torch.nn.ModuleList(torch.nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:], strict=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n = len(self.layers)
        for i, layer in enumerate(self.layers):
            x = F.linear(x, layer.weight, layer.bias)
            if i < n - 1:
                x = F.relu(x)
        return x


def check_bounds(bounds) -> np.ndarray:
    b = np.asarray(bounds, dtype=np.float64)
    if b.shape != (2, 3) or not np.all(np.isfinite(b)) or np.any(b[1] <= b[0]):
        raise DynslamError(f"map.bounds must be [[xmin,ymin,zmin],[xmax,ymax,zmax]] with min < max, got {bounds!r}")
    return b


class NeuralMap(torch.nn.Module):
    def __init__(self, cfg: MapConfig, bounds):
        super().__init__()
        b = check_bounds(bounds)
        self.cfg = cfg
        self.truncation = float(cfg.truncation)
        extent = float((b[1] - b[0]).max())
        finest = max(int(math.ceil(extent / cfg.voxel_size)), cfg.BASE_RESOLUTION)
        self.grid = HashGrid(cfg.n_levels, cfg.N_FEATURES, cfg.log2_hashmap_size, cfg.BASE_RESOLUTION,
                             finest, impl=cfg.HASHGRID_IMPL)
        self.blob = OneBlob(cfg.ONEBLOB_BINS, 3)
        h = cfg.hidden_dim
        # two linear layers each (Co-SLAM num_layers = 2); forward() writes them as split matmuls
        self.sdf_net = _MLP([self.grid.out_dim + self.blob.out_dim, h, 1 + cfg.GEO_FEAT_DIM])
        self.color_net = _MLP([self.blob.out_dim + cfg.GEO_FEAT_DIM, h, 3])
        self.register_buffer("bmin", torch.tensor(b[0], dtype=torch.float32))
        self.register_buffer("bsize", torch.tensor(b[1] - b[0], dtype=torch.float32))

    @property
    def bounds(self) -> np.ndarray:
        lo = self.bmin.detach().cpu().numpy().astype(np.float64)
        return np.stack([lo, lo + self.bsize.detach().cpu().numpy()])

    def normalize(self, pts: torch.Tensor) -> torch.Tensor:
        return (pts - self.bmin) / self.bsize

    def forward(self, pts: torch.Tensor, color: bool = True):
        """World points (N, 3) -> sdf (N,) in truncation units, rgb (N, 3) in [0, 1] (or None)."""
        sdf, rgb, _ = self.query(pts, color)
        return sdf, rgb

    def query(self, pts: torch.Tensor, color: bool = True, grid_extra: Optional[torch.Tensor] = None):
        """:meth:`forward`, plus the grid features of the world points ``grid_extra`` (M, 3) (as
        :meth:`grid_features`) from the same hash grid call, or None: one table gradient per
        mapping iteration instead of two when the smoothness loss needs features."""
        x = self.normalize(pts)
        blob = self.blob(x)
        g = self.grid.out_dim
        n = x.shape[0]
        if grid_extra is None:
            feats, extra = self.grid(x), None
        else:
            both = self.grid(torch.cat([x, self._grid_coords(grid_extra)]))
            feats, extra = both[:n], both[n:]
        # first layers as split matmuls (no concatenated copies): W [grid | blob] = W_g grid + W_b blob,
        # the second product accumulated in place (addmm_ runs the same GEMM as addmm without first
        # copying its (N, hidden) input into a fresh tensor), ReLU in place too
        l0, l1 = self.sdf_net.layers
        hid = F.linear(blob, l0.weight[:, g:], l0.bias).addmm_(feats, l0.weight[:, :g].t())
        h = F.linear(F.relu(hid, inplace=True), l1.weight, l1.bias)
        sdf = h[:, 0]
        if not color:
            return sdf, None, extra
        c0, c1 = self.color_net.layers
        nb = self.blob.out_dim
        hc = F.linear(blob, c0.weight[:, :nb], c0.bias).addmm_(h[:, 1:], c0.weight[:, nb:].t())
        rgb = torch.sigmoid(F.linear(F.relu(hc, inplace=True), c1.weight, c1.bias))
        return sdf, rgb, extra

    def _grid_coords(self, pts: torch.Tensor) -> torch.Tensor:
        """World points -> hash grid coordinates, clamped to the map's box."""
        return self.normalize(pts).clamp(0, 1)

    def grid_features(self, pts: torch.Tensor) -> torch.Tensor:
        return self.grid(self._grid_coords(pts))

    def map_parameters(self):
        return list(self.parameters())
