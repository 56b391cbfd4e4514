"""Least-squares similarity alignment of two point sets (Umeyama, PAMI 1991).

Independent numpy implementation, used to cross-check evo's alignment in the tests and by code
that needs an alignment without evo.
"""

from __future__ import annotations

import numpy as np

from dynslam_cli.errors import DynslamError


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """``(R, t, s)`` minimising ``sum ||dst_i - (s R src_i + t)||^2`` over rotations ``R``.

    ``src`` and ``dst`` are N×3 (row per point, the same point order).  Without ``with_scale``
    ``s`` is 1 (a rigid SE(3) fit).  Raises :class:`DynslamError` when the inputs have different
    shapes, fewer than 3 points, non-finite values, or (with scale) a degenerate source.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape != dst.shape or src.shape[1] < 2:
        raise DynslamError(f"umeyama: point sets must both be N×d with the same shape, got {src.shape} and {dst.shape}")
    n, d = src.shape
    if n < 3:
        raise DynslamError(f"umeyama: need at least 3 point pairs, got {n}")
    if not (np.isfinite(src).all() and np.isfinite(dst).all()):
        raise DynslamError("umeyama: point sets contain NaN or infinite values")
    mu_s = src.mean(axis=0)
    mu_d = dst.mean(axis=0)
    xs = src - mu_s
    xd = dst - mu_d
    cov = xd.T @ xs / n  # d×d cross-covariance Σ_dst,src
    u, sig, vt = np.linalg.svd(cov)
    sign = np.eye(d)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[-1, -1] = -1.0  # reflection -> nearest proper rotation
    r = u @ sign @ vt
    if with_scale:
        var_s = (xs ** 2).sum() / n
        if var_s <= 1e-18:
            raise DynslamError("umeyama: source points are all identical; the scale is undefined")
        s = float(np.trace(np.diag(sig) @ sign) / var_s)
    else:
        s = 1.0
    t = mu_d - s * r @ mu_s
    return r, t, s


def apply_similarity(points: np.ndarray, r: np.ndarray, t: np.ndarray, s: float = 1.0) -> np.ndarray:
    """``s R p + t`` for each row ``p`` of ``points``."""
    return s * np.asarray(points, dtype=np.float64) @ np.asarray(r).T + np.asarray(t)
