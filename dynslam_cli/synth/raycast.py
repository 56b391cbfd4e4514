"""Analytic ray casting of boxes and ellipsoids for every pixel at once (numba, parallel rows).

Primitives are grouped (one group per object); a group is skipped when the ray misses its
bounding sphere.  For each pixel the kernel returns the z-depth of the nearest hit, the instance
id, and the shaded colour (texture looked up by surface coordinates in metres, Lambertian
shading with one point light plus ambient).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from dynslam_cli.utils.threads import choose_numba_layer

choose_numba_layer()  # before any kernel here launches

TILE = 16  # pixels per side of the tiles whose viewing cones cull the object groups


@njit(cache=True, inline="always")
def _wrap(x: float) -> float:
    return x - math.floor(x)


@njit(cache=True)
def _tex_lookup(textures, tid, u, v, out):
    """Bilinear, wrapping lookup of texture ``tid`` at (u, v) in tile units; writes RGB into out."""
    s = textures.shape[1]
    x = _wrap(u) * s - 0.5
    y = _wrap(v) * s - 0.5
    x0 = int(math.floor(x))
    y0 = int(math.floor(y))
    fx = x - x0
    fy = y - y0
    x0 %= s
    y0 %= s
    x1 = (x0 + 1) % s
    y1 = (y0 + 1) % s
    for c in range(3):
        a = textures[tid, y0, x0, c] * (1.0 - fx) + textures[tid, y0, x1, c] * fx
        b = textures[tid, y1, x0, c] * (1.0 - fx) + textures[tid, y1, x1, c] * fx
        out[c] = a * (1.0 - fy) + b * fy


@njit(cache=True, parallel=True)
def raycast(
    cam_R, cam_t, fx, fy, cx, cy, width, height,
    group_centre, group_radius, group_box, group_ell,
    box_c, box_R, box_h, box_tex, box_scale, box_inside, box_inst,
    ell_c, ell_R, ell_r, ell_tex, ell_scale, ell_inst,
    textures, light, ambient,
):
    """Render one view.

    cam_R, cam_t: camera-to-world rotation (3x3) and centre (3).  group_box/group_ell: (G, 2)
    index ranges into the box / ellipsoid arrays.  box_R / ell_R: local-to-world rotations;
    box_h: half extents; ell_r: radii; *_tex: texture ids (boxes: one per face -x,+x,-y,+y,-z,+z);
    *_scale: metres per texture tile; box_inside: the box is seen from inside (the room).
    Returns depth (H, W) float64 z-depth in metres (0 = nothing hit), inst (H, W) int32 and
    rgb (H, W, 3) float32 in 0..255.
    """
    depth = np.zeros((height, width), np.float64)
    inst = np.zeros((height, width), np.int32)
    rgb = np.zeros((height, width, 3), np.float32)
    n_groups = group_centre.shape[0]
    ox, oy, oz = cam_t[0], cam_t[1], cam_t[2]
    # Group bounding spheres in the camera frame (for the per-tile cone test).
    gcam = np.zeros((n_groups, 3))
    for g in range(n_groups):
        px = group_centre[g, 0] - ox
        py = group_centre[g, 1] - oy
        pz = group_centre[g, 2] - oz
        for k in range(3):
            gcam[g, k] = cam_R[0, k] * px + cam_R[1, k] * py + cam_R[2, k] * pz
    tiles_x = (width + TILE - 1) // TILE
    tiles_y = (height + TILE - 1) // TILE
    for tile in prange(tiles_x * tiles_y):
        ty = tile // tiles_x
        tx = tile - ty * tiles_x
        u0 = tx * TILE
        v0 = ty * TILE
        u1 = min(u0 + TILE, width) - 1
        v1 = min(v0 + TILE, height) - 1
        # The tile's viewing cone: axis through its centre, half-angle to its corners.
        ax = ((u0 + u1) * 0.5 - cx) / fx
        ay = ((v0 + v1) * 0.5 - cy) / fy
        an = math.sqrt(ax * ax + ay * ay + 1.0)
        ax /= an
        ay /= an
        az = 1.0 / an
        cos_max = 1.0
        for cu in (u0 - 0.5, u1 + 0.5):
            for cv in (v0 - 0.5, v1 + 0.5):
                qx = (cu - cx) / fx
                qy = (cv - cy) / fy
                qn = math.sqrt(qx * qx + qy * qy + 1.0)
                cq = (qx * ax + qy * ay + az) / qn
                if cq < cos_max:
                    cos_max = cq
        theta = math.acos(min(1.0, max(-1.0, cos_max)))
        cand = np.empty(n_groups, np.int64)
        n_cand = 0
        for g in range(n_groups):
            r = group_radius[g]
            if r < 0.0:
                cand[n_cand] = g
                n_cand += 1
                continue
            dist = math.sqrt(gcam[g, 0] ** 2 + gcam[g, 1] ** 2 + gcam[g, 2] ** 2)
            if dist <= r:
                cand[n_cand] = g
                n_cand += 1
                continue
            cphi = (gcam[g, 0] * ax + gcam[g, 1] * ay + gcam[g, 2] * az) / dist
            phi = math.acos(min(1.0, max(-1.0, cphi)))
            if phi <= theta + math.asin(min(1.0, r / dist)) + 1e-6:
                cand[n_cand] = g
                n_cand += 1
        col = np.zeros(3)
        for v in range(v0, v1 + 1):
            for u in range(u0, u1 + 1):
                xc = (u - cx) / fx
                yc = (v - cy) / fy
                # World ray direction with unit z in the camera: t is the z-depth directly.
                dx = cam_R[0, 0] * xc + cam_R[0, 1] * yc + cam_R[0, 2]
                dy = cam_R[1, 0] * xc + cam_R[1, 1] * yc + cam_R[1, 2]
                dz = cam_R[2, 0] * xc + cam_R[2, 1] * yc + cam_R[2, 2]
                dd = dx * dx + dy * dy + dz * dz
                best = 1e30
                kind = -1  # 0 box, 1 ellipsoid
                idx = -1
                face = -1
                for ci in range(n_cand):
                    g = cand[ci]
                    # Bounding sphere test (skipped for the room: radius < 0).
                    r = group_radius[g]
                    if r > 0.0:
                        px = group_centre[g, 0] - ox
                        py = group_centre[g, 1] - oy
                        pz = group_centre[g, 2] - oz
                        tb = (px * dx + py * dy + pz * dz) / dd
                        qx = px - tb * dx
                        qy = py - tb * dy
                        qz = pz - tb * dz
                        if qx * qx + qy * qy + qz * qz > r * r:
                            continue
                        if tb < 0.0 and px * px + py * py + pz * pz > r * r:
                            continue
                    for b in range(group_box[g, 0], group_box[g, 1]):
                        # Ray in the box's local frame.
                        px = ox - box_c[b, 0]
                        py = oy - box_c[b, 1]
                        pz = oz - box_c[b, 2]
                        lo0 = box_R[b, 0, 0] * px + box_R[b, 1, 0] * py + box_R[b, 2, 0] * pz
                        lo1 = box_R[b, 0, 1] * px + box_R[b, 1, 1] * py + box_R[b, 2, 1] * pz
                        lo2 = box_R[b, 0, 2] * px + box_R[b, 1, 2] * py + box_R[b, 2, 2] * pz
                        ld0 = box_R[b, 0, 0] * dx + box_R[b, 1, 0] * dy + box_R[b, 2, 0] * dz
                        ld1 = box_R[b, 0, 1] * dx + box_R[b, 1, 1] * dy + box_R[b, 2, 1] * dz
                        ld2 = box_R[b, 0, 2] * dx + box_R[b, 1, 2] * dy + box_R[b, 2, 2] * dz
                        tmin = -1e30
                        tmax = 1e30
                        fmin = -1
                        fmax = -1
                        ok = True
                        for a in range(3):
                            if a == 0:
                                o_, d_ = lo0, ld0
                            elif a == 1:
                                o_, d_ = lo1, ld1
                            else:
                                o_, d_ = lo2, ld2
                            h = box_h[b, a]
                            if abs(d_) < 1e-12:
                                if o_ < -h or o_ > h:
                                    ok = False
                                    break
                                continue
                            t1 = (-h - o_) / d_
                            t2 = (h - o_) / d_
                            f1 = 2 * a
                            f2 = 2 * a + 1
                            if t1 > t2:
                                t1, t2 = t2, t1
                                f1, f2 = f2, f1
                            if t1 > tmin:
                                tmin = t1
                                fmin = f1
                            if t2 < tmax:
                                tmax = t2
                                fmax = f2
                        if not ok or tmin > tmax:
                            continue
                        if box_inside[b]:
                            if tmax > 1e-6 and tmax < best:
                                best = tmax
                                kind = 0
                                idx = b
                                face = fmax
                        else:
                            if tmin > 1e-6 and tmin < best:
                                best = tmin
                                kind = 0
                                idx = b
                                face = fmin
                    for e in range(group_ell[g, 0], group_ell[g, 1]):
                        px = ox - ell_c[e, 0]
                        py = oy - ell_c[e, 1]
                        pz = oz - ell_c[e, 2]
                        lo0 = (ell_R[e, 0, 0] * px + ell_R[e, 1, 0] * py + ell_R[e, 2, 0] * pz) / ell_r[e, 0]
                        lo1 = (ell_R[e, 0, 1] * px + ell_R[e, 1, 1] * py + ell_R[e, 2, 1] * pz) / ell_r[e, 1]
                        lo2 = (ell_R[e, 0, 2] * px + ell_R[e, 1, 2] * py + ell_R[e, 2, 2] * pz) / ell_r[e, 2]
                        ld0 = (ell_R[e, 0, 0] * dx + ell_R[e, 1, 0] * dy + ell_R[e, 2, 0] * dz) / ell_r[e, 0]
                        ld1 = (ell_R[e, 0, 1] * dx + ell_R[e, 1, 1] * dy + ell_R[e, 2, 1] * dz) / ell_r[e, 1]
                        ld2 = (ell_R[e, 0, 2] * dx + ell_R[e, 1, 2] * dy + ell_R[e, 2, 2] * dz) / ell_r[e, 2]
                        qa = ld0 * ld0 + ld1 * ld1 + ld2 * ld2
                        qb = lo0 * ld0 + lo1 * ld1 + lo2 * ld2
                        qc = lo0 * lo0 + lo1 * lo1 + lo2 * lo2 - 1.0
                        disc = qb * qb - qa * qc
                        if disc < 0.0:
                            continue
                        sq = math.sqrt(disc)
                        t = (-qb - sq) / qa
                        if t <= 1e-6:
                            continue  # camera inside or behind: not visible
                        if t < best:
                            best = t
                            kind = 1
                            idx = e
                if kind < 0:
                    continue
                hx = ox + best * dx
                hy = oy + best * dy
                hz = oz + best * dz
                if kind == 0:
                    b = idx
                    px = hx - box_c[b, 0]
                    py = hy - box_c[b, 1]
                    pz = hz - box_c[b, 2]
                    l0 = box_R[b, 0, 0] * px + box_R[b, 1, 0] * py + box_R[b, 2, 0] * pz
                    l1 = box_R[b, 0, 1] * px + box_R[b, 1, 1] * py + box_R[b, 2, 1] * pz
                    l2 = box_R[b, 0, 2] * px + box_R[b, 1, 2] * py + box_R[b, 2, 2] * pz
                    axis = face // 2
                    sign = 1.0 if face % 2 == 1 else -1.0
                    if box_inside[b]:
                        sign = -sign
                    nx = sign * box_R[b, 0, axis]
                    ny = sign * box_R[b, 1, axis]
                    nz = sign * box_R[b, 2, axis]
                    # Surface coordinates: the two other local axes, measured from the face corner.
                    if axis == 0:
                        su = l1 + box_h[b, 1]
                        sv = l2 + box_h[b, 2]
                    elif axis == 1:
                        su = l0 + box_h[b, 0]
                        sv = l2 + box_h[b, 2]
                    else:
                        su = l0 + box_h[b, 0]
                        sv = l1 + box_h[b, 1]
                    sc = box_scale[b]
                    _tex_lookup(textures, box_tex[b, face], su / sc, -sv / sc, col)
                    inst[v, u] = box_inst[b]
                else:
                    e = idx
                    px = hx - ell_c[e, 0]
                    py = hy - ell_c[e, 1]
                    pz = hz - ell_c[e, 2]
                    l0 = ell_R[e, 0, 0] * px + ell_R[e, 1, 0] * py + ell_R[e, 2, 0] * pz
                    l1 = ell_R[e, 0, 1] * px + ell_R[e, 1, 1] * py + ell_R[e, 2, 1] * pz
                    l2 = ell_R[e, 0, 2] * px + ell_R[e, 1, 2] * py + ell_R[e, 2, 2] * pz
                    # Normal: gradient of the implicit function, rotated to the world.
                    g0 = l0 / (ell_r[e, 0] * ell_r[e, 0])
                    g1 = l1 / (ell_r[e, 1] * ell_r[e, 1])
                    g2 = l2 / (ell_r[e, 2] * ell_r[e, 2])
                    nx = ell_R[e, 0, 0] * g0 + ell_R[e, 0, 1] * g1 + ell_R[e, 0, 2] * g2
                    ny = ell_R[e, 1, 0] * g0 + ell_R[e, 1, 1] * g1 + ell_R[e, 1, 2] * g2
                    nz = ell_R[e, 2, 0] * g0 + ell_R[e, 2, 1] * g1 + ell_R[e, 2, 2] * g2
                    nn = math.sqrt(nx * nx + ny * ny + nz * nz) + 1e-12
                    nx /= nn
                    ny /= nn
                    nz /= nn
                    # Surface coordinates: longitude arc length around the long (z) axis, and height.
                    ang = math.atan2(l1 / ell_r[e, 1], l0 / ell_r[e, 0])
                    rm = 0.5 * (ell_r[e, 0] + ell_r[e, 1])
                    su = (ang + math.pi) * rm
                    sv = l2 + ell_r[e, 2]
                    sc = ell_scale[e]
                    _tex_lookup(textures, ell_tex[e], su / sc, -sv / sc, col)
                    inst[v, u] = ell_inst[e]
                lx = light[0] - hx
                ly = light[1] - hy
                lz = light[2] - hz
                ld = math.sqrt(lx * lx + ly * ly + lz * lz) + 1e-12
                lam = (nx * lx + ny * ly + nz * lz) / ld
                if lam < 0.0:
                    lam = 0.0
                shade = ambient + (1.0 - ambient) * lam / (1.0 + 0.04 * ld * ld)
                depth[v, u] = best
                for c in range(3):
                    rgb[v, u, c] = col[c] * shade
    return depth, inst, rgb
