"""A tiny analytic RGB-D scene for tests and benchmarks: a room corner (back wall + floor), a
person-like cylinder standing on the floor and a box, seen by a pinhole camera at the origin
looking along +z (x right, y down)."""

from __future__ import annotations

import numpy as np

WALL_Z = 3.5
FLOOR_Y = 1.2  # camera height above the floor (y points down)


def toy_intrinsics(w: int, h: int) -> tuple[float, float, float, float]:
    f = 525.0 * w / 640.0
    return f, f, (w - 1) / 2.0, (h - 1) / 2.0


def render_toy(w: int = 320, h: int = 240, person_x: float = -0.3, person_z: float = 2.0,
               box_x: float | None = 0.9, box_z: float = 2.6, person: bool = True, seed: int = 0,
               noise: float = 0.0):
    """Returns (rgb uint8 H×W×3, depth float32 H×W metres, gt ids int32: 1 person, 2 box, 0 room)."""
    fx, fy, cx, cy = toy_intrinsics(w, h)
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rx, ry = (u - cx) / fx, (v - cy) / fy
    t = np.full((h, w), WALL_Z)
    kind = np.zeros((h, w), np.int32)  # 0 wall, 3 floor, 1 person, 2 box
    tf = np.where(ry > 1e-6, FLOOR_Y / np.maximum(ry, 1e-6), np.inf)
    m = tf < t
    t[m], kind[m] = tf[m], 3
    if person:  # vertical cylinder r = 0.25 from the floor up to 1.7 m
        r2 = 0.25 ** 2
        a = rx ** 2 + 1.0
        b = -2.0 * (person_x * rx + person_z)
        c = person_x ** 2 + person_z ** 2 - r2
        disc = b * b - 4 * a * c
        tc = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
        yc = ry * tc
        m = (disc >= 0) & (tc > 0) & (yc <= FLOOR_Y) & (yc >= FLOOR_Y - 1.7) & (tc < t)
        t[m], kind[m] = tc[m], 1
    if box_x is not None:  # box 0.6 wide, 0.5 high, front face at z = box_z
        tb = np.full((h, w), box_z)
        xb, yb = rx * tb, ry * tb
        m = (np.abs(xb - box_x) <= 0.3) & (yb >= FLOOR_Y - 0.5) & (yb <= FLOOR_Y) & (tb < t)
        t[m], kind[m] = tb[m], 2
    rng = np.random.default_rng(seed)
    rgb = np.zeros((h, w, 3), np.float64)
    X, Y = rx * t, ry * t
    wall = kind == 0
    rgb[wall] = [200, 190, 170]
    rgb[wall] += (20 * (np.sin(X[wall] * 8) > 0))[:, None]
    floor = kind == 3
    rgb[floor] = [120, 90, 60]
    rgb[floor] += (25 * ((np.floor(X[floor] * 2) + np.floor(t[floor] * 2)) % 2))[:, None]
    per = kind == 1
    shirt = Y < FLOOR_Y - 0.9
    rgb[per & shirt] = [200, 40, 40]
    rgb[per & ~shirt] = [30, 40, 120]
    rgb[per & (Y < FLOOR_Y - 1.45)] = [225, 180, 150]
    rgb[kind == 2] = [60, 160, 70]
    rgb += rng.normal(0, 3, rgb.shape)
    depth = t.astype(np.float32)
    if noise > 0:
        depth = depth + rng.normal(0, noise, depth.shape).astype(np.float32) * depth ** 2
    gt = np.where(kind == 1, 1, np.where(kind == 2, 2, 0)).astype(np.int32)
    return np.clip(rgb, 0, 255).astype(np.uint8), depth.astype(np.float32), gt
