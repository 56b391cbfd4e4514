"""The hash grid's numba path for torch: an autograd function over the CPU kernels of
:mod:`dynslam_cli.map._hashgrid_kernels` (their conventions and parallel layouts are described there),
and the layout switches the benchmark times (``FORWARD_PARALLEL``, ``X_GRAD_PARALLEL``).
Nothing here allocates a table gradient unless :func:`hashgrid_numba` is asked for one
(``embeddings.requires_grad``).
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from dynslam_cli.map._hashgrid_kernels import (  # noqa: F401 - the kernels are this module's API too
    P1, P2, backward_levels, backward_x_points, contract_jac, forward_levels, forward_levels_jac, forward_points,
    reduce_x)

# ---------------------------------------------------------------------------- torch glue
# Parallel layouts, measured with benchmarks/bench_hashgrid.py --kernels.  "levels": each thread
# works on whole levels, so it reads (and for the table gradient writes) one level's 2^log2 x F
# slice of the table at a time (cache-resident); "points": each thread owns a block of points and
# touches all levels.  Over levels measured 10-45 % faster single-threaded and equal or faster
# with 2 threads.
FORWARD_PARALLEL = "levels"
# x gradient without the table gradient (tracking): "jacobian" (forward_levels_jac stores the
# per-level Jacobian, the backward is contract_jac: one pass over the table instead of two),
# "levels" (backward_levels + reduce_x) or "points" (backward_x_points).  With the table gradient,
# backward_levels always computes both at once.
X_GRAD_PARALLEL = "jacobian"
_EMPTY3 = np.empty((0, 0, 0), np.float32)


def _sync_threads() -> None:
    n = max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))
    if numba.get_num_threads() != n:
        numba.set_num_threads(n)


def _np(t: torch.Tensor) -> np.ndarray:
    """A contiguous float32 numpy view (a copy only when t is not already contiguous)."""
    return t.detach().contiguous().numpy()


class _HashGridFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, table, res, dense, with_jac):
        _sync_threads()
        xn = _np(x)
        out = torch.empty(x.shape[0], table.shape[0] * table.shape[2], dtype=torch.float32)
        ctx.jac = None
        if with_jac:
            L, _, F = table.shape
            ctx.jac = np.empty((L, x.shape[0], F, 3), np.float32)
            forward_levels_jac(xn, _np(table), res, dense, out.numpy(), ctx.jac)
        else:
            fwd = forward_levels if FORWARD_PARALLEL == "levels" else forward_points
            fwd(xn, _np(table), res, dense, out.numpy())
        ctx.save_for_backward(x, table)
        ctx.res = res
        ctx.dense = dense
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):
        x, table = ctx.saved_tensors
        need_x, need_table = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        grad_x = grad_table = None
        if not (need_x or need_table):
            return None, None, None, None, None
        _sync_threads()
        xn = _np(x)
        gn = _np(grad_out.to(torch.float32))
        tn = _np(table)
        if need_x:
            grad_x = torch.empty(x.shape, dtype=torch.float32)
        if need_x and not need_table and ctx.jac is not None:
            contract_jac(xn, ctx.jac, gn, grad_x.numpy())
            return grad_x, None, None, None, None
        if need_x and not need_table and X_GRAD_PARALLEL == "points":
            backward_x_points(xn, tn, gn, ctx.res, ctx.dense, grad_x.numpy())
            return grad_x, None, None, None, None
        if need_table:
            grad_table = torch.empty(table.shape, dtype=torch.float32)  # zeroed by the kernel
            gt = grad_table.numpy()
        else:
            gt = _EMPTY3
        part = np.empty((table.shape[0], x.shape[0], 3), np.float32) if need_x else _EMPTY3
        backward_levels(xn, tn, gn, ctx.res, ctx.dense, need_table, need_x, gt, part)
        if need_x:
            reduce_x(xn, part, grad_x.numpy())
        return grad_x, grad_table, None, None, None


def level_arrays(resolutions, dense):
    """The per-level int64 resolutions and uint8 dense flags the kernels take."""
    return np.asarray(resolutions, dtype=np.int64), np.asarray(dense, dtype=np.uint8)


def hashgrid_numba(x: torch.Tensor, table: torch.Tensor, res: np.ndarray, dense: np.ndarray) -> torch.Tensor:
    """Encode ``x`` (N, 3) float32 CPU with ``table`` (L, T, F) float32 CPU; differentiable w.r.t.
    both (first order).  ``res, dense`` come from :func:`level_arrays`.  When only ``x`` needs a
    gradient (tracking) and ``X_GRAD_PARALLEL`` is ``"jacobian"``, the forward also stores the
    Jacobian so that the backward is a contraction."""
    with_jac = (X_GRAD_PARALLEL == "jacobian" and torch.is_grad_enabled() and x.requires_grad
                and not table.requires_grad)
    return _HashGridFunction.apply(x, table, res, dense, with_jac)
