"""Configuration of the neural map and its rendering (Co-SLAM settings, see BRIEF.md)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from dynslam_cli.config.fields import opt


@dataclass
class MapConfig:
    bounds: Optional[list] = opt(None, "Scene bounds [[xmin,ymin,zmin],[xmax,ymax,zmax]] in metres (world frame); null = from the first frame's depth plus `auto_margin`.")
    auto_margin: float = opt(2.0, "Margin (m) added around the first frame's points when bounds are null.")
    n_levels: int = opt(16, "Hash grid levels.")
    n_features: int = opt(2, "Features per level.")
    log2_hashmap_size: int = opt(16, "log2 of the hash table size per level (19 for large rooms).")
    base_resolution: int = opt(16, "Coarsest grid resolution.")
    voxel_size: float = opt(0.02, "Finest grid cell (m): finest resolution = largest bounds extent / voxel_size.")
    oneblob_bins: int = opt(16, "One-blob encoding bins per axis.")
    hidden_dim: int = opt(32, "Hidden width of the SDF and colour decoders.")
    geo_feat_dim: int = opt(15, "Geometry feature passed from the SDF to the colour decoder.")
    truncation: float = opt(0.10, "TSDF truncation tr (m). The paper uses 0.10; Co-SLAM's TUM config 0.05.")
    hashgrid_impl: str = opt("auto", "Hash grid implementation: auto (numba on CPU, torch on CUDA), numba, torch.")
