"""Multi-resolution hash grid encoding (Instant-NGP / tiny-cuda-nn ``HashGrid``, as in Co-SLAM).

Two implementations with identical semantics:

* ``torch``: plain PyTorch (autograd does the backward).  This is the reference and the CUDA path.
* ``numba``: a :class:`torch.autograd.Function` whose forward and backward are parallel numba
  kernels (``dynslam_cli.map._hashgrid_kernels``, called through ``_hashgrid_numba``); the CPU fast path.

``impl="auto"`` picks per call from the input: numba for float32 CPU tensors, torch otherwise
(CUDA tensors, float64 for ``gradcheck``, or numba not importable).

Grid convention (documented; both implementations follow it exactly)
-------------------------------------------------------------------
* per-level scale ``b = exp((ln finest - ln base) / (n_levels - 1))`` (``b = 1`` for one level);
* resolution of level ``l``: ``R_l = floor(base * b**l + 1e-6)`` (the epsilon keeps e.g. 512 from
  becoming 511 through rounding); level ``l`` has ``R_l`` cells and ``R_l + 1`` vertices per axis;
* input ``x`` in ``[0, 1]^3`` (normalised by the scene bounds), clamped to ``[0, 1]`` (the clamp
  has zero gradient outside, as ``torch.clamp``);
* ``pos = x * R_l`` (float32), cell ``c = clamp(floor(pos), 0, R_l - 1)``, fraction ``f = pos - c``
  (so ``x = 1`` lies at ``f = 1`` in the last cell).  This is *not* tcnn's ``scale = base*b^l - 1``,
  offset 0.5 convention: vertex ``k`` of level ``l`` sits exactly at ``x = k / R_l``;
* vertex index: dense ``i + j*(R+1) + k*(R+1)**2`` when ``(R+1)**3 <= T`` (table size
  ``T = 2**log2_hashmap_size``), else the spatial hash
  ``(i*1 xor j*2654435761 xor k*805459861) mod T`` (tcnn's primes; ``T`` is a power of two so the
  mod is a mask and uint32 wrap-around of the products does not change the result);
* trilinear interpolation of the 8 corner features; output ``(N, n_levels*n_features)``,
  level-major (``[l0f0, l0f1, l1f0, ...]``) like tcnn.
"""

from __future__ import annotations

import math
from typing import List

import torch

from dynslam_cli.errors import DynslamError

PRIMES = (1, 2654435761, 805459861)
IMPLS = ("auto", "numba", "torch")


def level_resolutions(n_levels: int, base_resolution: int, finest_resolution: int) -> List[int]:
    """Grid resolution (cells per axis) of every level."""
    if n_levels < 1:
        raise DynslamError(f"hash grid: n_levels must be >= 1, got {n_levels}")
    if base_resolution < 1 or finest_resolution < base_resolution:
        raise DynslamError(
            f"hash grid: need 1 <= base_resolution <= finest_resolution, got {base_resolution}, {finest_resolution}")
    if n_levels == 1:
        return [int(base_resolution)]
    b = math.exp((math.log(finest_resolution) - math.log(base_resolution)) / (n_levels - 1))
    return [int(math.floor(base_resolution * b ** level + 1e-6)) for level in range(n_levels)]


_NUMBA_KERNELS = False  # not tried yet; then the module or None


def _numba_module():
    """The numba kernels module, or None when numba cannot be imported (tried once)."""
    global _NUMBA_KERNELS
    if _NUMBA_KERNELS is False:
        try:
            from dynslam_cli.map import _hashgrid_numba
        except ImportError:  # numba missing or broken: the torch reference still works
            _hashgrid_numba = None
        _NUMBA_KERNELS = _hashgrid_numba
    return _NUMBA_KERNELS


class HashGrid(torch.nn.Module):
    """Multi-resolution hash grid; see the module docstring for the exact convention."""

    def __init__(self, n_levels: int = 16, n_features: int = 2, log2_hashmap_size: int = 16,
                 base_resolution: int = 16, finest_resolution: int = 512, impl: str = "auto"):
        super().__init__()
        if impl not in IMPLS:
            raise DynslamError(f"hash grid: impl must be one of {', '.join(IMPLS)}, got {impl!r}")
        if not 1 <= log2_hashmap_size <= 30:
            raise DynslamError(f"hash grid: log2_hashmap_size must be in 1..30, got {log2_hashmap_size}")
        if n_features < 1:
            raise DynslamError(f"hash grid: n_features must be >= 1, got {n_features}")
        self.n_levels = int(n_levels)
        self.n_features = int(n_features)
        self.log2_hashmap_size = int(log2_hashmap_size)
        self.table_size = 1 << self.log2_hashmap_size
        self.base_resolution = int(base_resolution)
        self.finest_resolution = int(finest_resolution)
        self.impl = impl
        self.out_dim = self.n_levels * self.n_features
        self.resolutions = level_resolutions(self.n_levels, self.base_resolution, self.finest_resolution)
        # dense[l]: level l indexes its (R+1)^3 vertices directly instead of hashing them
        self.dense = [(r + 1) ** 3 <= self.table_size for r in self.resolutions]
        self.embeddings = torch.nn.Parameter(
            torch.empty(self.n_levels, self.table_size, self.n_features, dtype=torch.float32).uniform_(-1e-4, 1e-4))
        # small per-level constants for the torch path (moved with .to(device), not saved)
        self.register_buffer("_res", torch.tensor(self.resolutions, dtype=torch.int64), persistent=False)
        self.register_buffer("_dense", torch.tensor(self.dense, dtype=torch.bool), persistent=False)
        self._level_arrays = None  # (int64 resolutions, uint8 dense flags) numpy arrays for numba

    def extra_repr(self) -> str:
        return (f"n_levels={self.n_levels}, n_features={self.n_features}, log2_hashmap_size={self.log2_hashmap_size}, "
                f"resolutions={self.resolutions[0]}..{self.resolutions[-1]}, impl={self.impl!r}")

    # ------------------------------------------------------------------ dispatch
    def resolve_impl(self, x: torch.Tensor) -> str:
        """The implementation a call with input ``x`` uses (``numba`` or ``torch``)."""
        if self.impl == "torch":
            return "torch"
        cpu32 = (x.device.type == "cpu" and x.dtype == torch.float32
                 and self.embeddings.device.type == "cpu" and self.embeddings.dtype == torch.float32)
        if self.impl == "numba":
            if not cpu32:
                raise DynslamError(
                    f"hash grid: impl 'numba' needs float32 CPU tensors, got x {x.dtype} on {x.device}, "
                    f"table {self.embeddings.dtype} on {self.embeddings.device} (use impl auto or torch)")
            if _numba_module() is None:
                raise DynslamError("hash grid: impl 'numba' requested but numba cannot be imported (use impl auto or torch)")
            return "numba"
        return "numba" if cpu32 and _numba_module() is not None else "torch"

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() != 2 or x.shape[1] != 3:
            raise DynslamError(f"hash grid: input must be (N, 3), got {tuple(x.shape)}")
        if self.resolve_impl(x) == "numba":
            kernels = _numba_module()
            if self._level_arrays is None:
                self._level_arrays = kernels.level_arrays(self.resolutions, self.dense)
            return kernels.hashgrid_numba(x, self.embeddings, *self._level_arrays)
        return self.forward_torch(x)

    # ------------------------------------------------------------------ reference
    def corner_indices(self, x: torch.Tensor):
        """Per-level corner table indices and trilinear weights.

        Returns ``idx`` (L, N, 8) int64 into the level's table and ``w`` (L, N, 8) (differentiable
        w.r.t. ``x``).  Corner ``k`` has offset bits ``(k & 1, k >> 1 & 1, k >> 2 & 1)`` on x, y, z.
        The 8 corners are built by broadcasting per-axis parts (memory O(L*N*8), not O(L*N*8*3)).
        """
        res = self._res.to(x.device)
        dense = self._dense.to(x.device).view(-1, 1, 1, 1, 1)
        xc = x.clamp(0.0, 1.0)
        pos = xc.unsqueeze(0) * res.to(x.dtype).view(-1, 1, 1)               # (L, N, 3)
        cell = torch.floor(pos).to(torch.int64)
        cell = torch.minimum(cell.clamp_min(0), (res - 1).view(-1, 1, 1))
        frac = pos - cell.to(x.dtype)                                          # (L, N, 3)
        both = torch.stack([cell, cell + 1], dim=-1)                           # (L, N, 3, 2) vertex coords
        stride = (res + 1).view(-1, 1, 1)
        # per-axis parts, combined below as a[..., m, j, i] so that the flat corner index is
        # k = i + 2 j + 4 m (x bit lowest)
        ax, ay, az = both[:, :, 0], both[:, :, 1], both[:, :, 2]              # (L, N, 2) each
        dense_idx = ((az * (stride * stride)).unsqueeze(-1).unsqueeze(-1)
                     + (ay * stride).unsqueeze(-2).unsqueeze(-1) + ax.unsqueeze(-2).unsqueeze(-2))
        hashed = (((az * PRIMES[2]).unsqueeze(-1).unsqueeze(-1) ^ (ay * PRIMES[1]).unsqueeze(-2).unsqueeze(-1)
                   ^ (ax * PRIMES[0]).unsqueeze(-2).unsqueeze(-2)) & (self.table_size - 1))
        idx = torch.where(dense, dense_idx, hashed).flatten(-3)                # (L, N, 8)
        wts = torch.stack([1 - frac, frac], dim=-1)                            # (L, N, 3, 2)
        wx, wy, wz = wts[:, :, 0], wts[:, :, 1], wts[:, :, 2]
        w = (wx.unsqueeze(-2) * wy.unsqueeze(-1)).unsqueeze(-3) * wz.unsqueeze(-1).unsqueeze(-1)
        return idx, w.flatten(-3)

    def forward_torch(self, x: torch.Tensor) -> torch.Tensor:
        """The plain-PyTorch reference (also the CUDA path)."""
        n = x.shape[0]
        idx, w = self.corner_indices(x)
        L, T, F = self.embeddings.shape
        offs = (torch.arange(L, device=x.device, dtype=torch.int64) * T).view(-1, 1, 1)
        table = self.embeddings.to(x.dtype).reshape(L * T, F)
        feats = table[(idx + offs).reshape(-1)].view(L, n, 8, F)               # (L, N, 8, F)
        out = (feats * w.unsqueeze(-1)).sum(dim=2)                             # (L, N, F)
        return out.permute(1, 0, 2).reshape(n, L * F)
