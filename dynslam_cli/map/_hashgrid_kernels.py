"""Numba CPU kernels of the hash grid (forward, backward w.r.t. the table and w.r.t. x); the torch
autograd glue that calls them is :mod:`dynslam_cli.map._hashgrid_numba`.

Same convention as :mod:`dynslam_cli.map.hashgrid` (see its docstring), float32 throughout:
``pos = clamp(x, 0, 1) * R`` in float32, cell ``c = min(int(pos), R - 1)``, ``f = pos - c``; corner
``k`` has offsets ``(k & 1, k >> 1 & 1, k >> 2 & 1)``; dense index ``i + j*(R+1) + k*(R+1)^2`` or
hash ``(i ^ j*2654435761 ^ k*805459861) & (T - 1)``.

Parallel layout (measured on the 2-core dev machine, see benchmarks/bench_hashgrid.py --kernels
and ``FORWARD_PARALLEL`` / ``X_GRAD_PARALLEL`` below):
* everything is parallel over levels by default (prange over levels, then points): a thread reads
  one level's table slice at a time, and the table gradient is scatter-added into the thread's own
  level slice (no races, no atomics); corner indices and weights are recomputed in the backward,
  not stored;
* the x gradient is written per level into an (L, N, 3) buffer and summed over levels by a
  points-parallel reduction (which also applies the clamp mask); with the table gradient both
  come out of one pass (``backward_levels``);
* points-parallel variants (``forward_points``, ``backward_x_points``) are kept, selectable, and
  timed by the benchmark.
The 8 corner indices are computed from per-axis parts (3 additions/xors each, one dense-vs-hash
branch per point and level), the weights as ``(w_x*w_y)*w_z`` like the reference.
Nothing here allocates a table gradient unless :func:`hashgrid_numba` is asked for one
(``embeddings.requires_grad``).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from dynslam_cli.utils.threads import choose_numba_layer

choose_numba_layer()  # before any kernel here launches

P1 = np.int64(2654435761)
P2 = np.int64(805459861)
U1 = np.uint32(P1)
U2 = np.uint32(P2)


@njit(inline="always")
def _clamp01(v):
    if v < np.float32(0.0):
        return np.float32(0.0)
    if v > np.float32(1.0):
        return np.float32(1.0)
    return v


@njit(inline="always")
def _cell_frac(v, rf, rm1):
    """Cell and fraction along one axis: ``p = v*R`` (float32), ``c = min(floor(p), R-1)`` (``rm1`` = R-1, int32)."""
    p = v * rf
    # p >= 0, so truncation is floor; the max keeps a NaN input (undefined cast) inside the table
    c = min(max(np.int32(p), np.int32(0)), rm1)
    return c, p - np.float32(c)


@njit(inline="always")
def _corner_indices(c0, c1, c2, dense, stride, mask):
    """Table indices of the 8 corners (corner k: offsets k & 1, k >> 1 & 1, k >> 2 & 1), unsigned:
    the hash's bits under ``mask`` (< 2^32) are those of the 64-bit products, a dense index is below
    the table size, and an unsigned index needs no negative-index wraparound (the forward took
    0.79-0.82x, the table backward 0.87-0.90x the time of the same code on int64 indices)."""
    a0 = np.uint32(c0)
    a1 = a0 + np.uint32(1)
    if dense:
        b0 = np.uint32(c1) * stride
        b1 = b0 + stride
        s2 = stride * stride
        d0 = np.uint32(c2) * s2
        d1 = d0 + s2
        return (a0 + b0 + d0, a1 + b0 + d0, a0 + b1 + d0, a1 + b1 + d0,
                a0 + b0 + d1, a1 + b0 + d1, a0 + b1 + d1, a1 + b1 + d1)
    b0 = np.uint32(c1) * U1
    b1 = b0 + U1
    d0 = np.uint32(c2) * U2
    d1 = d0 + U2
    return ((a0 ^ b0 ^ d0) & mask, (a1 ^ b0 ^ d0) & mask, (a0 ^ b1 ^ d0) & mask, (a1 ^ b1 ^ d0) & mask,
            (a0 ^ b0 ^ d1) & mask, (a1 ^ b0 ^ d1) & mask, (a0 ^ b1 ^ d1) & mask, (a1 ^ b1 ^ d1) & mask)


@njit(inline="always")
def _point_corners(x, n, rf, r, dn, mask):
    """Corner indices and fractions of point ``x[n]`` (clamped) at one level: ``(ids, f0, f1, f2)``."""
    rm1 = np.int32(r - 1)
    c0, f0 = _cell_frac(_clamp01(x[n, 0]), rf, rm1)
    c1, f1 = _cell_frac(_clamp01(x[n, 1]), rf, rm1)
    c2, f2 = _cell_frac(_clamp01(x[n, 2]), rf, rm1)
    return _corner_indices(c0, c1, c2, dn, np.uint32(r + 1), mask), f0, f1, f2


@njit(inline="always")
def _corner_weights(f0, f1, f2):
    """Trilinear weights of the 8 corners, ``(w_x * w_y) * w_z`` as the reference multiplies."""
    one = np.float32(1.0)
    e0 = one - f0
    e1 = one - f1
    e2 = one - f2
    q00 = e0 * e1
    q10 = f0 * e1
    q01 = e0 * f1
    q11 = f0 * f1
    return (q00 * e2, q10 * e2, q01 * e2, q11 * e2, q00 * f2, q10 * f2, q01 * f2, q11 * f2)


@njit(inline="always")
def _interpolate(table, lv, ids, ws, f):
    """Feature ``f`` of level ``lv`` at a point: the corners' values weighted, summed in corner order."""
    acc = np.float32(0.0)
    for k in range(8):
        acc += ws[k] * table[lv, ids[k], f]
    return acc


@njit(parallel=True, fastmath=False, cache=True)
def forward_points(x, table, res, dense, out):
    """out[n, l*F + f] = trilinear interpolation of level l; parallel over points."""
    n_pts = x.shape[0]
    n_lv, tsize, nf = table.shape
    mask = np.uint32(tsize - 1)
    for n in prange(n_pts):
        for lv in range(n_lv):
            r = res[lv]
            ids, f0, f1, f2 = _point_corners(x, n, np.float32(r), r, dense[lv] != 0, mask)
            ws = _corner_weights(f0, f1, f2)
            for f in range(nf):
                out[n, lv * nf + f] = _interpolate(table, lv, ids, ws, f)


@njit(parallel=True, fastmath=False, cache=True)
def forward_levels(x, table, res, dense, out):
    """Same as :func:`forward_points`, parallel over levels (each thread reads one level's table)."""
    n_pts = x.shape[0]
    n_lv, tsize, nf = table.shape
    mask = np.uint32(tsize - 1)
    for lv in prange(n_lv):
        r = res[lv]
        rf = np.float32(r)
        dn = dense[lv] != 0
        for n in range(n_pts):
            ids, f0, f1, f2 = _point_corners(x, n, rf, r, dn, mask)
            ws = _corner_weights(f0, f1, f2)
            for f in range(nf):
                out[n, lv * nf + f] = _interpolate(table, lv, ids, ws, f)


@njit(parallel=True, fastmath=False, cache=True)
def forward_levels_jac(x, table, res, dense, out, jac):
    """:func:`forward_levels` (same values, same summation order) that also writes the Jacobian
    ``jac[l, n, f, :]`` = d out[n, l*F+f] / d (clamped) x[n] (before the clamp mask): along x it is
    ``R * sum over the 4 (y, z) corner pairs of (t(x=1) - t(x=0)) * w_y * w_z``, likewise for y, z.
    The tracking backward then needs no second pass over the table (:func:`contract_jac`)."""
    n_pts = x.shape[0]
    n_lv, tsize, nf = table.shape
    mask = np.uint32(tsize - 1)
    one = np.float32(1.0)
    for lv in prange(n_lv):
        r = res[lv]
        rf = np.float32(r)
        dn = dense[lv] != 0
        for n in range(n_pts):
            ids, f0, f1, f2 = _point_corners(x, n, rf, r, dn, mask)
            ws = _corner_weights(f0, f1, f2)
            e0 = one - f0
            e1 = one - f1
            e2 = one - f2
            for f in range(nf):
                t0 = table[lv, ids[0], f]
                t1 = table[lv, ids[1], f]
                t2 = table[lv, ids[2], f]
                t3 = table[lv, ids[3], f]
                t4 = table[lv, ids[4], f]
                t5 = table[lv, ids[5], f]
                t6 = table[lv, ids[6], f]
                t7 = table[lv, ids[7], f]
                acc = np.float32(0.0)
                acc += ws[0] * t0
                acc += ws[1] * t1
                acc += ws[2] * t2
                acc += ws[3] * t3
                acc += ws[4] * t4
                acc += ws[5] * t5
                acc += ws[6] * t6
                acc += ws[7] * t7
                out[n, lv * nf + f] = acc
                jac[lv, n, f, 0] = rf * ((t1 - t0) * (e1 * e2) + (t3 - t2) * (f1 * e2)
                                         + (t5 - t4) * (e1 * f2) + (t7 - t6) * (f1 * f2))
                jac[lv, n, f, 1] = rf * ((t2 - t0) * (e0 * e2) + (t3 - t1) * (f0 * e2)
                                         + (t6 - t4) * (e0 * f2) + (t7 - t5) * (f0 * f2))
                jac[lv, n, f, 2] = rf * ((t4 - t0) * (e0 * e1) + (t5 - t1) * (f0 * e1)
                                         + (t6 - t2) * (e0 * f1) + (t7 - t3) * (f0 * f1))


@njit(inline="always")
def _corner_dx(table, lv, ids, grad_out, n, nf, f0, f1, f2):
    """Level ``lv``'s derivative of ``sum_f grad_out[n, lv*F+f] * feature_f`` along x, y, z per unit
    of cell (multiply by R): with ``s_k = sum_f grad_out[n, lv*F+f] * table[lv, ids[k], f]``, the
    sum over the 4 corner pairs along each axis of (s_k(1) - s_k(0)) times the other two weights."""
    zero = np.float32(0.0)
    one = np.float32(1.0)
    s0 = zero
    s1 = zero
    s2 = zero
    s3 = zero
    s4 = zero
    s5 = zero
    s6 = zero
    s7 = zero
    for f in range(nf):
        go = grad_out[n, lv * nf + f]
        s0 += go * table[lv, ids[0], f]
        s1 += go * table[lv, ids[1], f]
        s2 += go * table[lv, ids[2], f]
        s3 += go * table[lv, ids[3], f]
        s4 += go * table[lv, ids[4], f]
        s5 += go * table[lv, ids[5], f]
        s6 += go * table[lv, ids[6], f]
        s7 += go * table[lv, ids[7], f]
    e0 = one - f0
    e1 = one - f1
    e2 = one - f2
    d0 = (s1 - s0) * (e1 * e2) + (s3 - s2) * (f1 * e2) + (s5 - s4) * (e1 * f2) + (s7 - s6) * (f1 * f2)
    d1 = (s2 - s0) * (e0 * e2) + (s3 - s1) * (f0 * e2) + (s6 - s4) * (e0 * f2) + (s7 - s5) * (f0 * f2)
    d2 = (s4 - s0) * (e0 * e1) + (s5 - s1) * (f0 * e1) + (s6 - s2) * (e0 * f1) + (s7 - s3) * (f0 * f1)
    return d0, d1, d2


@njit(parallel=True, fastmath=False, cache=True)
def contract_jac(x, jac, grad_out, grad_x):
    """grad_x[n, d] = sum over levels and features of grad_out[n, l*F+f] * jac[l, n, f, d], zero
    where the clamp is active (as :func:`reduce_x`)."""
    n_lv, _, nf, _ = jac.shape
    zero = np.float32(0.0)
    one = np.float32(1.0)
    for n in prange(x.shape[0]):
        g0 = zero
        g1 = zero
        g2 = zero
        for lv in range(n_lv):
            for f in range(nf):
                go = grad_out[n, lv * nf + f]
                g0 += go * jac[lv, n, f, 0]
                g1 += go * jac[lv, n, f, 1]
                g2 += go * jac[lv, n, f, 2]
        v = x[n, 0]
        grad_x[n, 0] = g0 if (v >= zero and v <= one) else zero
        v = x[n, 1]
        grad_x[n, 1] = g1 if (v >= zero and v <= one) else zero
        v = x[n, 2]
        grad_x[n, 2] = g2 if (v >= zero and v <= one) else zero


@njit(parallel=True, fastmath=False, cache=True)
def backward_levels(x, table, grad_out, res, dense, do_table, do_x, grad_table, gx_part):
    """Backward parallel over levels; the corner indices and weights are recomputed from x.

    ``do_table``: ``grad_table[l, idx, f] = sum over points and corners of w * grad_out[n, l*F+f]``
    (each thread zeroes and scatter-adds into its own level's slice: no races, no atomics).
    ``do_x``: ``gx_part[l, n, :]`` = level l's contribution to d loss / d x[n] (before the clamp
    mask), summed over levels by :func:`reduce_x`.  With ``s_k = sum_f grad_out[n, l*F+f] *
    table[l, idx_k, f]`` the derivative along x is ``R * sum over the 4 (y, z) corner pairs of
    (s_k(x=1) - s_k(x=0)) * w_y * w_z``, likewise for y and z.  Arrays not asked for may be empty.
    """
    n_pts = x.shape[0]
    n_lv, tsize, nf = table.shape
    mask = np.uint32(tsize - 1)
    zero = np.float32(0.0)
    for lv in prange(n_lv):
        if do_table:
            grad_table[lv] = zero
        r = res[lv]
        rf = np.float32(r)
        dn = dense[lv] != 0
        for n in range(n_pts):
            ids, f0, f1, f2 = _point_corners(x, n, rf, r, dn, mask)
            if do_table:
                ws = _corner_weights(f0, f1, f2)
                for f in range(nf):
                    g = grad_out[n, lv * nf + f]
                    for k in range(8):
                        grad_table[lv, ids[k], f] += ws[k] * g
            if do_x:
                d0, d1, d2 = _corner_dx(table, lv, ids, grad_out, n, nf, f0, f1, f2)
                gx_part[lv, n, 0] = rf * d0
                gx_part[lv, n, 1] = rf * d1
                gx_part[lv, n, 2] = rf * d2


@njit(parallel=True, fastmath=False, cache=True)
def reduce_x(x, gx_part, grad_x):
    """grad_x[n, d] = sum over levels of gx_part[l, n, d], zero where the clamp is active
    (x outside [0, 1]; torch.clamp passes the gradient at exactly 0 and 1)."""
    n_lv = gx_part.shape[0]
    zero = np.float32(0.0)
    one = np.float32(1.0)
    for n in prange(x.shape[0]):
        for d in range(3):
            g = zero
            for lv in range(n_lv):
                g += gx_part[lv, n, d]
            v = x[n, d]
            grad_x[n, d] = g if (v >= zero and v <= one) else zero


@njit(parallel=True, fastmath=False, cache=True)
def backward_x_points(x, table, grad_out, res, dense, grad_x):
    """The x gradient alone, parallel over points (each point owns its row), same formula and
    summation order as :func:`backward_levels` + :func:`reduce_x`; benchmark alternative."""
    n_pts = x.shape[0]
    n_lv, tsize, nf = table.shape
    mask = np.uint32(tsize - 1)
    zero = np.float32(0.0)
    one = np.float32(1.0)
    for n in prange(n_pts):
        r0 = x[n, 0]
        r1 = x[n, 1]
        r2 = x[n, 2]
        x0 = _clamp01(r0)
        x1 = _clamp01(r1)
        x2 = _clamp01(r2)
        g0 = zero
        g1 = zero
        g2 = zero
        for lv in range(n_lv):
            r = res[lv]
            rf = np.float32(r)
            rm1 = np.int32(r - 1)
            c0, f0 = _cell_frac(x0, rf, rm1)
            c1, f1 = _cell_frac(x1, rf, rm1)
            c2, f2 = _cell_frac(x2, rf, rm1)
            ids = _corner_indices(c0, c1, c2, dense[lv] != 0, np.uint32(r + 1), mask)
            d0, d1, d2 = _corner_dx(table, lv, ids, grad_out, n, nf, f0, f1, f2)
            g0 += d0 * rf
            g1 += d1 * rf
            g2 += d2 * rf
        grad_x[n, 0] = g0 if (r0 >= zero and r0 <= one) else zero
        grad_x[n, 1] = g1 if (r1 >= zero and r1 <= one) else zero
        grad_x[n, 2] = g2 if (r2 >= zero and r2 <= one) else zero
