"""Configuration of the neural map and its rendering (Co-SLAM settings, see BRIEF.md)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional

from dynslam_cli.config.fields import numbers, opt


@dataclass
class MapConfig:
    bounds: Optional[list] = opt(None, "Scene bounds [[xmin,ymin,zmin],[xmax,ymax,zmax]] in metres (world frame); null = "
                                 "from the first frame's depth plus a 2 m margin.")
    n_levels: int = opt(16, "Hash grid levels.", min=1)
    log2_hashmap_size: int = opt(16, "log2 of the hash table size per level (19 for large rooms).", min=1, max=32)
    voxel_size: float = opt(0.02, "Finest grid cell (m): finest resolution = largest bounds extent / voxel_size.", above=0)
    hidden_dim: int = opt(32, "Hidden width of the SDF and colour decoders.", min=1)
    truncation: float = opt(0.10, "TSDF truncation tr (m). The paper uses 0.10; Co-SLAM's TUM config 0.05.", above=0)
    # --- sampling along rays (depth-guided; about 16 samples per ray in all) ---
    near: float = opt(0.1, "Nearest sample distance (m, along the camera z axis).", min=0)
    far: float = opt(5.0, "Farthest sample distance (m) for rays without a depth measurement.", above=0)
    samples_surface: int = opt(12, "Samples per ray stratified in the band depth ± surface_range.", min=1)
    surface_range: float = opt(0.15, "Half-width (m) of the depth-guided sample band (Co-SLAM: 0.25 with 21 samples).", above=0)
    # --- losses (Co-SLAM definitions) ---
    w_rgb: float = opt(1.0, "Weight of the colour loss (MSE of rendered colour).", min=0)
    w_depth: float = opt(0.1, "Weight of the depth loss (MSE of rendered depth, valid depth only).", min=0)
    w_sdf: float = opt(5000.0, "Weight of the SDF loss (samples inside the truncation band).", min=0)
    w_free: float = opt(10.0, "Weight of the free-space loss (samples in front of the band regress to tr).", min=0)

    # Constants of the map (not keys: nobody has a reason to change them; Co-SLAM's values).
    N_FEATURES: ClassVar[int] = 2  # features per hash grid level
    BASE_RESOLUTION: ClassVar[int] = 16  # coarsest grid resolution
    ONEBLOB_BINS: ClassVar[int] = 16  # one-blob encoding bins per axis
    GEO_FEAT_DIM: ClassVar[int] = 15  # geometry feature passed from the SDF to the colour decoder
    # Hash grid implementation: auto = numba on CPU, torch on CUDA.
    HASHGRID_IMPL: ClassVar[str] = "auto"
    SAMPLES_FREE: ClassVar[int] = 4  # free-space samples per ray stratified in [near, depth - surface_range]
    W_SMOOTH: ClassVar[float] = 1e-8  # weight of the feature smoothness loss (mapping only)
    SMOOTH_GRID: ClassVar[int] = 8  # points per axis of the random cube used by the smoothness loss
    SMOOTH_VOXEL: ClassVar[float] = 0.1  # spacing (m) of the smoothness cube's points
    RGB_MISSING: ClassVar[float] = 0.05  # weight of the colour loss on rays without depth (Co-SLAM rgb_missing)

    def validate(self, key):
        """Cross-field and list rules (see config.fields)."""
        if not self.near < self.far:
            yield f"{key('near')} must be < {key('far')} (got {self.near:g} >= {self.far:g})"
        if self.bounds is not None:
            rows = self.bounds if isinstance(self.bounds, list) and len(self.bounds) == 2 else None
            lo, hi = (numbers(rows[0], 3), numbers(rows[1], 3)) if rows else (None, None)
            if lo is None or hi is None:
                yield f"{key('bounds')} must be null or [[xmin,ymin,zmin],[xmax,ymax,zmax]] (got {self.bounds!r})"
            elif not all(a < b for a, b in zip(lo, hi, strict=True)):
                yield f"{key('bounds')} must have each minimum < its maximum (got {self.bounds!r})"
