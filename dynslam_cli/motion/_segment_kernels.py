"""Numba kernels of the geometric segmenter (:mod:`dynslam_cli.motion.segment_geometric`): surface
normals and the edge tests, one pass over the image each instead of numpy's whole-array
temporaries, float32 throughout, with numpy's order of operations (``np.cross``, a norm summed
x, y, z, thresholds cast to float32 as numpy casts a Python scalar against a float32 array), so
the edges are the ones the numpy expressions give, bit for bit (tests/test_motion_segment.py);
and the growth of segments through continuous depth (a breadth-first queue).
They release the GIL: a run segments the next frame in a background thread (run/ahead.py)."""

from __future__ import annotations

import numpy as np
from numba import njit

from dynslam_cli.utils.threads import choose_numba_layer

choose_numba_layer()


@njit(cache=True, nogil=True)
def points(dm: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The h×w×3 point image ``(d·u[x], d·v[y], d)`` of a depth image ``dm`` (h×w) and the
    normalised image coordinates ``u`` (w) and ``v`` (h)."""
    h, w = dm.shape
    P = np.empty((h, w, 3), np.float32)
    for y in range(h):
        for x in range(w):
            d = dm[y, x]
            P[y, x, 0] = d * u[x]
            P[y, x, 1] = d * v[y]
            P[y, x, 2] = d
    return P


@njit(cache=True, nogil=True)
def normals(S: np.ndarray, wsum: np.ndarray) -> np.ndarray:
    """Unit normals (h×w×3 float32) of the point image ``P = S / max(wsum, 1e-6)`` (``S`` h×w×3,
    ``wsum`` h×w: a box-filtered point image and its box-filtered validity) from central
    differences over 2 px: ``cross(P[y, x+1] - P[y, x-1], P[y+1, x] - P[y-1, x])``; a difference
    that would reach past the image is 0 (so the normal is 0 on the border rows and columns)."""
    h, w, _ = S.shape
    P = np.empty((h, w, 3), np.float32)
    lo = np.float32(1e-6)
    for y in range(h):
        for x in range(w):
            q = max(wsum[y, x], lo)
            for c in range(3):
                P[y, x, c] = S[y, x, c] / q
    n = np.zeros((h, w, 3), np.float32)
    tiny = np.float32(1e-12)
    for y in range(1, h - 1):
        for x in range(1, w - 1):
            a0 = P[y, x + 1, 0] - P[y, x - 1, 0]
            a1 = P[y, x + 1, 1] - P[y, x - 1, 1]
            a2 = P[y, x + 1, 2] - P[y, x - 1, 2]
            b0 = P[y + 1, x, 0] - P[y - 1, x, 0]
            b1 = P[y + 1, x, 1] - P[y - 1, x, 1]
            b2 = P[y + 1, x, 2] - P[y - 1, x, 2]
            c0 = a1 * b2 - a2 * b1
            c1 = a2 * b0 - a0 * b2
            c2 = a0 * b1 - a1 * b0
            norm = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
            if norm < tiny:
                norm = tiny
            n[y, x, 0] = c0 / norm
            n[y, x, 1] = c1 / norm
            n[y, x, 2] = c2 / norm
    return n


@njit(inline="always")
def _step_edge(dm, lab, use_lab, y0, x0, y1, x1, depth_jump, color_jump, color_step):
    da = dm[y0, x0]
    db = dm[y1, x1]
    if da <= 0 or db <= 0:
        return False
    dmin = min(da, db)
    step = abs(da - db)
    if step > depth_jump * dmin:
        return True
    if use_lab:
        e0 = lab[y0, x0, 0] - lab[y1, x1, 0]
        e1 = lab[y0, x0, 1] - lab[y1, x1, 1]
        e2 = lab[y0, x0, 2] - lab[y1, x1, 2]
        dc = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        return dc > color_jump and step > color_step * dmin
    return False


@njit(cache=True, nogil=True)
def step_edges(dm: np.ndarray, lab: np.ndarray, depth_jump: float, color_jump: float,
               color_step: float) -> np.ndarray:
    """Edge mask (h×w bool): pixels without depth (``dm`` ≤ 0), and both pixels of every
    4-neighbour pair with depth whose depth steps by more than ``depth_jump``·d (d the nearer), or
    whose Lab colour (``lab`` h×w×3; an empty array = no colour test) differs by more than
    ``color_jump`` while the depth also steps by more than ``color_step``·d."""
    h, w = dm.shape
    use_lab = lab.shape[0] == h
    dj, cj, cs = np.float32(depth_jump), np.float32(color_jump), np.float32(color_step)
    edge = np.zeros((h, w), np.bool_)
    for y in range(h):
        for x in range(w):
            if dm[y, x] <= 0:
                edge[y, x] = True
            if y + 1 < h and _step_edge(dm, lab, use_lab, y, x, y + 1, x, dj, cj, cs):
                edge[y, x] = True
                edge[y + 1, x] = True
            if x + 1 < w and _step_edge(dm, lab, use_lab, y, x, y, x + 1, dj, cj, cs):
                edge[y, x] = True
                edge[y, x + 1] = True
    return edge


@njit(inline="always")
def _turns(n, y0, x0, y1, x1, cos_max):
    dot = n[y0, x0, 0] * n[y1, x1, 0] + n[y0, x0, 1] * n[y1, x1, 1] + n[y0, x0, 2] * n[y1, x1, 2]
    return dot < cos_max


@njit(cache=True, nogil=True)
def crease_edges(n: np.ndarray, smooth: np.ndarray, offset: int, cos_max: float, edge: np.ndarray) -> None:
    """Adds to ``edge`` (in place) both pixels of every pair ``offset`` px apart along a row or a
    column, both ``smooth``, whose normals (``n``) turn by more than arccos(``cos_max``)."""
    h, w = smooth.shape
    c = np.float32(cos_max)
    for y in range(h):
        for x in range(w):
            if not smooth[y, x]:
                continue
            if y + offset < h and smooth[y + offset, x] and _turns(n, y, x, y + offset, x, c):
                edge[y, x] = True
                edge[y + offset, x] = True
            if x + offset < w and smooth[y, x + offset] and _turns(n, y, x, y, x + offset, c):
                edge[y, x] = True
                edge[y, x + offset] = True


@njit(cache=True)
def grow_continuous(labels: np.ndarray, dm: np.ndarray, depth_jump: float) -> np.ndarray:
    """Seeded region growing through continuous depth: every unlabelled pixel (``labels`` 0) with
    depth (``dm`` > 0) that a 4-connected path of pixels with depth reaches from a labelled one
    without a step over ``depth_jump``·d (d the nearer) takes the label of the nearest such seed
    (breadth first, so in path length; ties go to the seed scanned first).  Returns a new int32
    label image; pixels without depth and pixels cut off by depth steps stay 0."""
    h, w = labels.shape
    out = labels.astype(np.int32).copy()
    queue = np.empty(h * w, np.int64)
    tail = 0
    for y in range(h):
        for x in range(w):
            if out[y, x] > 0 and dm[y, x] > 0:
                queue[tail] = y * w + x
                tail += 1
    dj = np.float32(depth_jump)
    head = 0
    while head < tail:
        idx = queue[head]
        head += 1
        y = idx // w
        x = idx - y * w
        dp = dm[y, x]
        for k in range(4):
            yy, xx = y, x
            if k == 0:
                yy = y - 1
            elif k == 1:
                yy = y + 1
            elif k == 2:
                xx = x - 1
            else:
                xx = x + 1
            if yy < 0 or yy >= h or xx < 0 or xx >= w or out[yy, xx] > 0:
                continue
            dq = dm[yy, xx]
            if dq <= 0 or abs(dp - dq) > dj * min(dp, dq):
                continue
            out[yy, xx] = out[y, x]
            queue[tail] = yy * w + xx
            tail += 1
    return out
