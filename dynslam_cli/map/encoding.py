"""One-blob encoding (Müller et al. 2019, as tcnn's ``OneBlob`` used by Co-SLAM).

Each coordinate ``x`` in [0, 1] activates ``n_bins`` bins with a Gaussian kernel of width
``sigma = 1 / n_bins`` evaluated at the bin centres ``(k + 0.5) / n_bins``:
``out[k] = exp(-(x - c_k)^2 / (2 sigma^2))``.  Differentiable w.r.t. ``x`` (tracking needs it).
Output layout: axis-major ``[x bins..., y bins..., z bins...]``.
"""

from __future__ import annotations

import torch


class OneBlob(torch.nn.Module):
    def __init__(self, n_bins: int = 16, n_dims: int = 3):
        super().__init__()
        self.n_bins = int(n_bins)
        self.n_dims = int(n_dims)
        self.out_dim = self.n_bins * self.n_dims
        centres = (torch.arange(self.n_bins, dtype=torch.float32) + 0.5) / self.n_bins
        self.register_buffer("centres", centres, persistent=False)
        self.inv_two_sigma2 = 0.5 * self.n_bins * self.n_bins

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        d = x.unsqueeze(-1) - self.centres.to(x.dtype)          # (N, D, B)
        if torch.is_grad_enabled() and x.requires_grad:
            return torch.exp(-(d * d) * self.inv_two_sigma2).reshape(x.shape[0], self.out_dim)
        # no gradient to x (mapping with fixed poses, rendering): the same values in place, in the
        # one (N, D, B) buffer; each fresh buffer of that size costs page faults worth several
        # times the arithmetic on it.  -(d*d)*k == (d*d)*(-k) exactly (IEEE negation).
        return d.mul_(d).mul_(-self.inv_two_sigma2).exp_().reshape(x.shape[0], self.out_dim)
