"""Scene content: the room, furniture, articulated walkers, a ball, camera trajectories, presets.

World frame: metres, z up, the floor at z = 0; the room spans x in [-2.5, 2.5], y in [-2, 2],
z in [0, 2.7].  The hand-held camera stands near (0, -1) and mostly looks along +y, where the
movers act.  Times are in seconds; a preset is built for a fixed duration so that its story
(enter, pick up, carry, ...) fits the number of frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from dynslam_cli.synth import textures as tx
from dynslam_cli.synth.geometry import (
    Parts, Path2D, camera_rotation, look_at, rot_x, rot_y, rot_z, smoothstep,
)

ROOM_MIN = np.array([-2.5, -2.0, 0.0])
ROOM_MAX = np.array([2.5, 2.0, 2.7])
LIGHT = np.array([0.3, -0.2, 2.5])
AMBIENT = 0.35


# ----------------------------------------------------------------------------- objects


@dataclass
class StaticObject:
    name: str
    id: int
    parts: Parts


@dataclass
class Mover:
    name: str
    id: int
    at: Callable[[float], Parts]  # time (s) -> primitives


@dataclass
class Scene:
    textures: np.ndarray
    room: Parts
    statics: list[StaticObject]
    movers: list[Mover]
    camera: Callable[[float], tuple[np.ndarray, np.ndarray]]  # t -> (R_c2w, centre)
    light: np.ndarray = field(default_factory=lambda: LIGHT.copy())
    ambient: float = AMBIENT


def transformed(p: Parts, R: np.ndarray, t: np.ndarray) -> Parts:
    out = Parts()
    for c, Rl, h, tex, sc in zip(p.box_c, p.box_R, p.box_h, p.box_tex, p.box_scale, strict=True):
        out.box(R @ c + t, h, R @ Rl, tex, sc)
    for c, Rl, r, tex, sc in zip(p.ell_c, p.ell_R, p.ell_r, p.ell_tex, p.ell_scale, strict=True):
        out.ellipsoid(R @ c + t, r, R @ Rl, tex, sc)
    return out


def room_parts(bank: tx.TextureBank, rng: np.random.Generator) -> Parts:
    walls = [bank.add(tx.wall(rng, posters=int(rng.integers(2, 5)))) for _ in range(4)]
    floor = bank.add(tx.planks(rng) if rng.random() < 0.5 else tx.tiles(rng))
    ceil = bank.add(tx.ceiling(rng))
    centre = (ROOM_MIN + ROOM_MAX) / 2
    half = (ROOM_MAX - ROOM_MIN) / 2
    # Faces: -x, +x, -y, +y walls, -z floor, +z ceiling.
    return Parts().box(centre, half, tex=[walls[0], walls[1], walls[2], walls[3], floor, ceil], scale=2.5)


# ----------------------------------------------------------------------------- furniture


def _table(w, d, h, top_tex, leg_tex) -> Parts:
    p = Parts().box((0, 0, h - 0.02), (w / 2, d / 2, 0.02), tex=top_tex, scale=1.2)
    for sx in (-1, 1):
        for sy in (-1, 1):
            p.box((sx * (w / 2 - 0.05), sy * (d / 2 - 0.05), (h - 0.04) / 2), (0.025, 0.025, (h - 0.04) / 2),
                  tex=leg_tex, scale=0.5)
    return p


def _shelf(w, d, h, frame_tex, book_texs, rng) -> Parts:
    t = 0.02
    p = Parts()
    for sx in (-1, 1):
        p.box((sx * (w / 2 - t), 0, h / 2), (t, d / 2, h / 2), tex=frame_tex, scale=1.0)
    p.box((0, d / 2 - 0.005, h / 2), (w / 2 - 2 * t, 0.005, h / 2), tex=frame_tex, scale=1.0)  # back
    levels = np.linspace(0.05, h - t, 5)
    for z in levels:
        p.box((0, 0, z), (w / 2 - 2 * t, d / 2, t), tex=frame_tex, scale=1.0)
    for z0, z1 in zip(levels[:-1], levels[1:], strict=True):
        x = -w / 2 + 3 * t
        while True:
            bw = rng.uniform(0.03, 0.09)
            if x + bw > w / 2 - 3 * t:
                break
            if rng.random() < 0.8:
                bh = min(rng.uniform(0.6, 0.9) * (z1 - z0 - 2 * t), z1 - z0 - 2 * t - 0.01)
                bd = rng.uniform(0.6, 0.9) * d / 2
                p.box((x + bw / 2, d / 2 - bd - 0.01, z0 + t + bh / 2), (bw / 2 - 0.002, bd, bh / 2),
                      tex=int(rng.choice(book_texs)), scale=0.3)
            x += bw
    return p


def _cabinet(w, d, h, body_tex, top_tex, handle_tex) -> Parts:
    p = Parts().box((0, 0, h / 2 - 0.01), (w / 2, d / 2, h / 2 - 0.01), tex=body_tex, scale=0.9)
    p.box((0, 0, h - 0.01), (w / 2 + 0.02, d / 2 + 0.02, 0.01), tex=top_tex, scale=1.0)
    n_doors = 2 if w > 0.6 else 1
    for k in range(n_doors):
        x = -w / 2 + (k + 0.5) * w / n_doors + (0.1 if k == 0 and n_doors == 2 else -0.1 if n_doors == 2 else 0.15)
        p.box((x, -d / 2 - 0.015, h * 0.7), (0.01, 0.015, 0.08), tex=handle_tex, scale=0.2)
    return p


def _desk_items(rng, w, d, h, texs) -> Parts:
    p = Parts()
    # A monitor on a stand, a keyboard and a few boxes.
    mw = rng.uniform(0.45, 0.6)
    p.box((0, d / 4, h + 0.18 + 0.15), (mw / 2, 0.02, 0.15), tex=texs[0], scale=0.6)
    p.box((0, d / 4 + 0.03, h + 0.09), (0.03, 0.02, 0.09), tex=texs[1], scale=0.3)
    p.box((0, -d / 6, h + 0.012), (0.22, 0.07, 0.012), tex=texs[1], scale=0.3)
    for _ in range(int(rng.integers(1, 4))):
        bw, bd, bh = rng.uniform(0.06, 0.2, 3)
        x = rng.uniform(-w / 2 + bw, w / 2 - bw)
        side = -1 if x < 0 else 1
        x = side * max(abs(x), mw / 2 + bw + 0.02)
        if abs(x) + bw > w / 2:
            continue
        p.box((x, rng.uniform(-d / 4, d / 4), h + bh), (bw, bd, bh), R=rot_z(rng.uniform(-0.5, 0.5)),
              tex=int(rng.choice(texs)), scale=0.4)
    return p


def build_furniture(bank: tx.TextureBank, rng: np.random.Generator, first_id: int = 1) -> list[StaticObject]:
    """Furniture along the walls, leaving the middle of the room free for the movers."""
    wood = [bank.add(tx.planks(rng, n=int(rng.integers(3, 8)))) for _ in range(2)]
    paint = [bank.add(tx.painted(rng)) for _ in range(4)]
    books = [bank.add(tx.painted(rng)) for _ in range(2)] + [bank.add(tx.fabric(rng))]
    objs: list[tuple[str, Parts, float, np.ndarray]] = []

    def jitter():
        return rng.uniform(-0.04, 0.04)

    # The side walls stay free for y < 0.7: walkers come in from there (out of the camera's view).
    # Far wall (y = +2): a book shelf and a low cabinet, facing -y.
    sw, sd, sh = rng.uniform(1.0, 1.3), rng.uniform(0.3, 0.4), rng.uniform(1.6, 2.0)
    sx = rng.uniform(-1.5 + sw / 2, -0.15)
    objs.append(("shelf", _shelf(sw, sd, sh, wood[0], books, rng), np.pi + jitter(),
                 np.array([sx, 2.0 - sd / 2 - 0.03, 0.0])))
    cw, cd, ch = rng.uniform(0.7, 1.0), rng.uniform(0.4, 0.55), rng.uniform(0.7, 1.0)
    cx = rng.uniform(sx + sw / 2 + cw / 2 + 0.1, max(sx + sw / 2 + cw / 2 + 0.1, 1.8 - cw / 2))
    objs.append(("cabinet", _cabinet(cw, cd, ch, paint[0], wood[1], paint[3]), np.pi + jitter(),
                 np.array([cx, 2.0 - cd / 2 - 0.03, 0.0])))
    # Left wall (x = -2.5), far end: a table with items, facing +x.
    tw, td, th = rng.uniform(1.0, 1.2), rng.uniform(0.6, 0.75), rng.uniform(0.72, 0.78)
    ty = rng.uniform(0.75 + tw / 2, 1.95 - tw / 2)
    table = _table(tw, td, th, wood[1], paint[1])
    items = _desk_items(rng, tw, td, th, [paint[2], paint[3], books[0], books[2]])
    for k in range(len(items.box_c)):
        table.box(items.box_c[k], items.box_h[k], items.box_R[k], items.box_tex[k], items.box_scale[k])
    objs.append(("table", table, -np.pi / 2 + jitter(), np.array([-2.5 + td / 2 + 0.05, ty, 0.0])))
    # Right wall (x = +2.5), far end: a tall wardrobe, facing -x.
    ww, wd, wh = rng.uniform(0.8, 1.1), rng.uniform(0.5, 0.6), rng.uniform(1.8, 2.1)
    wy = rng.uniform(0.75 + ww / 2, 1.95 - ww / 2)
    objs.append(("wardrobe", _cabinet(ww, wd, wh, paint[1], paint[2], paint[0]), np.pi / 2 + jitter(),
                 np.array([2.5 - wd / 2 - 0.03, wy, 0.0])))
    # Back wall (y = -2): a desk with a monitor and a drawer cabinet, facing +y.
    kw, kd, kh = rng.uniform(1.2, 1.5), rng.uniform(0.6, 0.7), rng.uniform(0.72, 0.78)
    kx = rng.uniform(-1.6, 0.2)
    desk = _table(kw, kd, kh, paint[2], paint[0])
    items = _desk_items(rng, kw, kd, kh, [paint[1], paint[3], books[1], wood[0]])
    for k in range(len(items.box_c)):
        desk.box(items.box_c[k], items.box_h[k], items.box_R[k], items.box_tex[k], items.box_scale[k])
    objs.append(("desk", desk, 0.0 + jitter(), np.array([kx, -2.0 + kd / 2 + 0.05, 0.0])))
    dw, dd, dh = rng.uniform(0.5, 0.8), rng.uniform(0.4, 0.5), rng.uniform(0.6, 0.9)
    dx = rng.uniform(kx + kw / 2 + dw / 2 + 0.1, 2.4 - dw / 2)
    objs.append(("drawers", _cabinet(dw, dd, dh, paint[3], wood[0], paint[2]), 0.0 + jitter(),
                 np.array([dx, -2.0 + dd / 2 + 0.05, 0.0])))
    # Objects are built with their front on the local -y side; the yaws above give the direction
    # their back faces (the wall behind them), so turn them round by pi.
    out = []
    for k, (name, parts, yaw, pos) in enumerate(objs):
        placed = transformed(parts, rot_z(yaw + np.pi), pos)
        # A slightly turned object may poke into its wall: push it back in (5 mm gap).
        lo, hi = placed.aabb()
        shift = np.maximum(0.0, ROOM_MIN + 0.005 - lo) - np.maximum(0.0, hi - (ROOM_MAX - 0.005))
        shift[2] = 0.0
        out.append(StaticObject(name, first_id + k, transformed(placed, np.eye(3), shift)))
    return out


# ----------------------------------------------------------------------------- walkers


class Walker:
    """A person-like articulated figure (~1.72 m): ellipsoids for torso, pelvis, head and limbs.

    ``motion(t) -> (pos (2,), heading rad, distance walked m)`` drives it; the gait phase follows
    the distance walked so the feet do not slide; limbs swing only while it moves.  ``carry(t)``
    (0..1) raises the arms to the front; ``bend(t)`` (0..1) bends the upper body forward.
    """

    def __init__(self, bank: tx.TextureBank, rng: np.random.Generator, motion,
                 carry=None, bend=None, height: float | None = None):
        self.motion = motion
        self.carry = carry or (lambda t: 0.0)
        self.bend = bend or (lambda t: 0.0)
        self.k = (height or rng.uniform(1.62, 1.85)) / 1.75
        self.shirt = bank.add(tx.fabric(rng))
        self.trousers = bank.add(tx.fabric(rng))
        self.skin = bank.add(tx.skin(rng))
        self.shoes = bank.add(tx.painted(rng))
        self.stride = 1.3 * self.k

    def speed(self, t: float) -> float:
        """Recent walking speed (backward difference: limbs start swinging once it has moved)."""
        dt = 0.1
        return abs(self.motion(t)[2] - self.motion(t - dt)[2]) / dt

    def at(self, t: float) -> Parts:
        pos, heading, dist = self.motion(t)
        k = self.k
        amp = float(np.clip(self.speed(t) / 0.7, 0.0, 1.0))
        phase = 2 * np.pi * dist / self.stride
        carry = float(self.carry(t))
        bend = float(self.bend(t))
        R = rot_z(heading)  # local x forward, y left, z up
        base = np.array([pos[0], pos[1], 0.0])

        def W(p):  # local -> world
            return R @ np.asarray(p, float) + base

        hip_z = 0.92 * k + 0.015 * amp * np.cos(2 * phase)
        hip = np.array([0.0, 0.0, hip_z])
        Rb = rot_y(0.55 * bend)  # bend forward about the hip (local y axis)

        def U(p):  # upper-body point (relative to the hip), bent, to world
            return W(hip + Rb @ np.asarray(p, float))

        p = Parts()
        Rw = R @ Rb
        p.ellipsoid(W(hip + [0, 0, 0.02]), (0.11 * k, 0.17 * k, 0.11 * k), R, self.trousers, 0.5)
        p.ellipsoid(U([0, 0, 0.30 * k]), (0.115 * k, 0.19 * k, 0.31 * k), Rw, self.shirt, 0.6)
        p.ellipsoid(U([0, 0, 0.63 * k]), (0.05 * k, 0.05 * k, 0.06 * k), Rw, self.skin, 0.35)  # neck
        p.ellipsoid(U([0.01, 0, 0.75 * k]), (0.10 * k, 0.085 * k, 0.12 * k), Rw, self.skin, 0.4)
        for side in (1, -1):  # left (+y), right (-y)
            ph = phase + (0 if side == 1 else np.pi)
            a = amp * 0.42 * np.sin(ph)
            knee = 0.08 + amp * 0.55 * max(0.0, np.sin(ph + np.pi / 2)) ** 2
            h = hip + [0, side * 0.09 * k, -0.02]
            kn = h + 0.45 * k * np.array([np.sin(a), 0, -np.cos(a)])
            an = kn + 0.44 * k * np.array([np.sin(a - knee), 0, -np.cos(a - knee)])
            p.segment(W(h), W(kn), 0.075 * k, self.trousers, 0.5)
            p.segment(W(kn), W(an), 0.055 * k, self.trousers, 0.5)
            p.ellipsoid(W(an + [0.07 * k, 0, -0.03]), (0.12 * k, 0.05 * k, 0.04 * k), R, self.shoes, 0.3)
            # Arms: swing opposite to the leg on the same side; carrying raises them to the front.
            b = (1 - carry) * (-amp * 0.35 * np.sin(ph)) + carry * 1.1
            elbow = (1 - carry) * (0.15 + 0.25 * amp) + carry * 0.45
            sh = np.array([0.0, side * 0.22 * k, 0.52 * k])
            el = sh + 0.29 * k * np.array([np.sin(b), -side * 0.05 * carry, -np.cos(b)])
            wr = el + 0.27 * k * np.array([np.sin(b + elbow), -side * 0.25 * carry, -np.cos(b + elbow)])
            p.segment(U(sh), U(el), 0.05 * k, self.shirt, 0.6)
            p.segment(U(el), U(wr), 0.04 * k, self.skin, 0.35)
            p.ellipsoid(U(wr + (wr - el) * 0.2), (0.045 * k, 0.045 * k, 0.045 * k), Rw, self.skin, 0.35)
        return p

    def body_points(self, pos: np.ndarray) -> np.ndarray:
        """Points on a cylinder enclosing the walker standing at floor positions pos (..., 2):
        (..., 96, 3).  Any of them in the image means the walker may be seen."""
        pos = np.asarray(pos, float)
        ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        ring = 0.42 * np.stack([np.cos(ang), np.sin(ang)], axis=1)
        out = []
        for z in (0.02, 0.5 * self.k, 0.9 * self.k, 1.3 * self.k, 1.6 * self.k, 1.8 * self.k):
            for r in ring:
                xy = pos + r
                out.append(np.concatenate([xy, np.full(pos.shape[:-1] + (1,), z)], axis=-1))
        return np.stack(out, axis=-2)


class PathMotion:
    """Walk along ``path`` at ``speed`` starting at time ``t0`` (standing at the start before),
    accelerating over ``ramp`` seconds; closed paths loop forever, open ones stop at the end."""

    def __init__(self, path: Path2D, speed: float, t0: float, ramp: float = 0.6, s0: float = 0.0):
        self.path, self.speed, self.t0, self.ramp, self.s0 = path, speed, t0, ramp, s0

    def dist(self, t: float) -> float:
        tau = t - self.t0
        if tau <= 0:
            d = 0.0
        elif tau < self.ramp:
            d = self.speed * tau * tau / (2 * self.ramp)
        else:
            d = self.speed * (tau - self.ramp / 2)
        if not self.path.closed:
            d = min(d, self.path.length - self.s0)
        return d

    def __call__(self, t: float):
        d = self.dist(t)
        pos, heading = self.path.at(self.s0 + d)
        return pos, heading, d


class Itinerary:
    """Walk legs at given times, standing (and turning smoothly) in between.

    legs: list of (t_start, t_end, Path2D open).  Each leg eases in and out (smoothstep).
    """

    def __init__(self, legs):
        self.legs = legs

    def __call__(self, t: float):
        done = 0.0
        prev_end = None
        for t0, t1, path in self.legs:
            if t < t0:
                start_pos, start_head = path.at(0.0)
                if prev_end is None:
                    return start_pos, start_head, done
                p_prev, h_prev, t_prev = prev_end
                w = smoothstep((t - t_prev) / max(t0 - t_prev, 1e-6))
                dh = (start_head - h_prev + np.pi) % (2 * np.pi) - np.pi
                return p_prev, h_prev + w * dh, done
            if t <= t1:
                s = path.length * smoothstep((t - t0) / max(t1 - t0, 1e-6))
                pos, head = path.at(s)
                return pos, head, done + s
            done += path.length
            end_pos, end_head = path.at(path.length)
            prev_end = (end_pos, end_head, t1)
        return prev_end[0], prev_end[1], done


# ----------------------------------------------------------------------------- cameras


class HandHeld:
    """A hand-held camera: smooth wandering translation (~1-2 m per 5 s), yaw sweeps, pitch and
    roll wobble, plus a small high-frequency shake (sums of sines with seeded phases)."""

    def __init__(self, rng: np.random.Generator, centre=None, focus=None, sweep: float = 1.0,
                 pitch0: float = -0.12):
        self.sweep = sweep
        self.pitch0 = pitch0
        self.c0 = np.array(centre if centre is not None else
                           [rng.uniform(-0.3, 0.3), rng.uniform(-1.1, -0.9), rng.uniform(1.3, 1.6)])
        # The operator keeps the camera roughly on ``focus`` (a floor point, or t -> point): the
        # yaw sweeps are centred on its direction from the current camera position.
        self.focus = focus if callable(focus) else (lambda t, f=np.asarray(
            (0.0, 0.6) if focus is None else focus, float): f)
        self.yaw0 = np.pi / 2
        self.ph = rng.uniform(0, 2 * np.pi, 16)
        self.f = np.array([rng.uniform(0.09, 0.13), rng.uniform(0.12, 0.18), rng.uniform(0.15, 0.25),
                           rng.uniform(0.1, 0.13), rng.uniform(0.25, 0.32), rng.uniform(0.14, 0.2),
                           rng.uniform(0.2, 0.26)])
        self.shake_f = rng.uniform(1.5, 5.0, 12)
        self.shake_ph = rng.uniform(0, 2 * np.pi, 12)

    def _shake(self, t: float, k: int) -> float:
        f, ph = self.shake_f[3 * k:3 * k + 3], self.shake_ph[3 * k:3 * k + 3]
        return float(np.sum(np.sin(2 * np.pi * f * t + ph)) / 3)

    def offset(self, t: float) -> np.ndarray:
        s = np.sin
        f, ph = self.f, self.ph
        return np.array([
            0.55 * s(2 * np.pi * f[0] * t + ph[0]) + 0.08 * s(2 * np.pi * f[2] * 2 * t + ph[8]),
            0.25 * s(2 * np.pi * f[1] * t + ph[1]),
            0.07 * s(2 * np.pi * f[2] * t + ph[2]),
        ]) + 0.0015 * np.array([self._shake(t, 0), self._shake(t, 1), self._shake(t, 2)])

    def wobble(self, t: float) -> tuple[float, float, float]:
        """Yaw sweep, pitch and roll wobble plus shake (radians, about the base direction)."""
        s = np.sin
        f, ph = self.f, self.ph
        dyaw = self.sweep * (0.3 * s(2 * np.pi * f[3] * t + ph[3]) + 0.08 * s(2 * np.pi * f[4] * t + ph[4]))
        dpitch = 0.06 * s(2 * np.pi * f[5] * t + ph[5])
        droll = 0.03 * s(2 * np.pi * f[6] * t + ph[6])
        return (dyaw + 0.003 * self._shake(t, 3), dpitch + 0.002 * self._shake(t, 1),
                droll + 0.0015 * self._shake(t, 2))

    def angles(self, t: float) -> tuple[float, float, float]:
        c = self.c0 + self.offset(t)
        f0 = np.asarray(self.focus(t), float)
        yaw0 = float(np.arctan2(f0[1] - c[1], f0[0] - c[0]))
        dyaw, dpitch, droll = self.wobble(t)
        return yaw0 + dyaw, self.pitch0 + dpitch, droll

    def __call__(self, t: float):
        return camera_rotation(*self.angles(t)), self.c0 + self.offset(t)


class FollowCam:
    """A camera carried behind a walker along its (closed) path, looking at its chest."""

    def __init__(self, rng, walker_motion: PathMotion, gap: float, height: float):
        self.m = walker_motion
        self.gap = gap
        self.height = height
        self.shake = HandHeld(rng, centre=np.zeros(3))

    def __call__(self, t: float):
        d = self.m.dist(t)
        pos_w, _ = self.m.path.at(self.m.s0 + d)
        pos_c, _ = self.m.path.at(self.m.s0 + d - self.gap)
        off = 0.4 * self.shake.offset(t)
        eye = np.array([pos_c[0], pos_c[1], self.height]) + off
        target = np.array([pos_w[0], pos_w[1], 1.15])
        dyaw, dpitch, droll = self.shake.wobble(t)
        R = look_at(eye, target, roll=droll)
        # Keep only a fraction of the operator's wobble so that the walker stays in view.
        return R @ rot_x(-0.3 * dpitch) @ rot_y(0.3 * dyaw), eye


# ----------------------------------------------------------------------------- visibility


def project_visible(points: np.ndarray, R: np.ndarray, c: np.ndarray, intr, width: int, height: int,
                    margin: float = 0.0) -> np.ndarray:
    """Whether world points (..., 3) project inside the image (with a margin in pixels)."""
    fx, fy, cx, cy = intr
    pc = (points - c) @ R  # world -> camera: R^T (p - c)
    z = pc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = fx * pc[..., 0] / z + cx
        v = fy * pc[..., 1] / z + cy
    return (z > 0.3) & (u >= margin) & (u <= width - 1 - margin) & (v >= margin) & (v <= height - 1 - margin)


def choose_start(walker: Walker, path: Path2D, speed: float, camera, times: np.ndarray, intr, width, height,
                 enter_frame: int) -> float:
    """Start time of a PathMotion along ``path`` such that the walker first shows up in the image
    at about ``enter_frame`` (its path starts out of view)."""
    n = len(times)
    step = 0.05
    s_grid = np.arange(0.0, path.length + step, step)
    pos = np.array([path.at(s)[0] for s in s_grid])
    pts = walker.body_points(pos)  # (K, 2, 3)
    vis = np.zeros((n, len(s_grid)), bool)
    for i, t in enumerate(times):
        R, c = camera(t)
        vis[i] = project_visible(pts, R, c, intr, width, height).any(axis=-1)
    best, best_err = 0.0, None
    for t0 in np.linspace(-4.0, times[-1], 240):
        m = PathMotion(path, speed, t0)
        idx = np.array([min(int(round(m.dist(t) / step)), len(s_grid) - 1) for t in times])
        v = vis[np.arange(n), idx]
        first = int(np.argmax(v)) if v.any() else n + 10
        after = v[first:].mean() if first < n else 0.0
        err = abs(first - enter_frame) + (0 if first >= enter_frame else 2) + 5 * n * (after < 0.5) * (1 - after)
        if best_err is None or err < best_err - 1e-9:
            best, best_err = float(t0), err
    return best


# ----------------------------------------------------------------------------- presets


PRESETS = ("static", "walker", "crowd", "kidnap", "balloon", "tracking")


def _loop_points(rng, x0, x1, y0, y1):
    j = lambda: rng.uniform(-0.15, 0.15)  # noqa: E731
    return [(x0 + j(), y0 + j()), (x1 + j(), y1 + j()), (x1 + j(), y0 + j()), (x0 + j(), y1 + j())]


def _walking_path(rng, start, loop, speed, duration) -> Path2D:
    """An open path from ``start`` (out of view) through ``loop`` repeated to last ``duration``."""
    perim = sum(np.linalg.norm(np.subtract(loop[k], loop[k - 1])) for k in range(len(loop)))
    reps = int(np.ceil((speed * (duration + 6.0)) / max(perim, 1e-3))) + 1
    return Path2D([start] + list(loop) * reps, closed=False)


def build_scene(preset: str, seed: int, frames: int, fps: float, intr, width: int, height: int) -> Scene:
    """The scene of ``preset`` for a sequence of ``frames`` frames (deterministic per seed)."""
    ss = np.random.SeedSequence([seed, PRESETS.index(preset) if preset in PRESETS else 99])
    r_cam, r_move = (np.random.default_rng(s) for s in ss.spawn(2))
    # Room and furniture depend only on the seed, not on the preset.
    r_room = np.random.default_rng(np.random.SeedSequence([seed, 1000]))
    bank = tx.TextureBank()
    room = room_parts(bank, r_room)
    statics = build_furniture(bank, r_room, first_id=1)
    next_id = len(statics) + 1
    duration = frames / fps
    times = np.arange(frames) / fps
    enter = max(1, int(round(0.1 * frames)))
    movers: list[Mover] = []
    camera = HandHeld(r_cam, focus=(0.0, 0.6))

    if preset == "static":
        pass
    elif preset == "walker":
        speed = r_move.uniform(0.9, 1.2)
        path = _walking_path(r_move, (-2.2, -0.9), _loop_points(r_move, -1.2, 1.2, 0.2, 1.0), speed, duration)
        w = Walker(bank, r_move, None)
        t0 = choose_start(w, path, speed, camera, times, intr, width, height, enter)
        w.motion = PathMotion(path, speed, t0)
        movers.append(Mover("walker", next_id, w.at))
    elif preset == "crowd":
        specs = [  # start (out of view), loop box, target enter fraction
            ((2.2, -0.9), (-1.1, 1.1, -0.15, 0.35), 0.10),
            ((-2.2, -0.8), (-1.3, 1.2, 0.5, 1.0), 0.18),
            ((2.2, -0.75), (-1.0, 1.3, 0.3, 1.0), 0.3),
            ((-2.2, -0.95), (-1.2, 0.9, 0.0, 0.9), 0.42),
        ]
        for k, (start, (x0, x1, y0, y1), frac) in enumerate(specs):
            speed = r_move.uniform(0.8, 1.3)
            loop = _loop_points(r_move, x0, x1, y0, y1)
            if k % 2 == 0:
                loop = loop[::-1]
            path = _walking_path(r_move, start, loop, speed, duration)
            w = Walker(bank, r_move, None)
            t0 = choose_start(w, path, speed, camera, times, intr, width, height, max(1, int(round(frac * frames))))
            w.motion = PathMotion(path, speed, t0)
            movers.append(Mover(f"walker{k + 1}", next_id + k, w.at))
    elif preset == "kidnap":
        movers.extend(_kidnap(bank, r_move, duration, next_id))
        box = movers[0].at
        mid = (box(0.0).box_c[0] + box(duration).box_c[0])[:2] / 2
        camera = HandHeld(r_cam, focus=lambda t: 0.5 * mid + 0.5 * box(t).box_c[0][:2], sweep=0.5, pitch0=-0.3)
    elif preset == "balloon":
        ball = _balloon(bank, r_move, camera, duration, fps, next_id)
        movers.append(ball)
        # The operator follows the ball with the camera once it has been thrown in.
        t_follow = 0.1 * duration + 0.3

        def focus(t, ball=ball.at):
            w = 0.5 * smoothstep((t - t_follow) / 0.5)
            return (1 - w) * np.array([0.0, 0.6]) + w * ball(t).ell_c[0][:2]

        camera.focus = focus  # unchanged up to the throw, so the launch point stays out of view
    elif preset == "tracking":
        loop = [(-1.1, -0.7), (1.1, -0.75), (1.15, 0.85), (-1.1, 0.85)]
        loop = [(x + r_move.uniform(-0.1, 0.1), y + r_move.uniform(-0.1, 0.1)) for x, y in loop]
        if r_move.random() < 0.5:
            loop = loop[::-1]
        path = Path2D(loop, closed=True)
        speed = r_move.uniform(0.8, 1.0)
        motion = PathMotion(path, speed, t0=enter / fps, s0=r_move.uniform(0, path.length))
        w = Walker(bank, r_move, motion)
        movers.append(Mover("walker", next_id, w.at))
        camera = FollowCam(r_cam, motion, gap=1.8, height=r_cam.uniform(1.4, 1.6))
    else:
        from dynslam_cli.errors import DynslamError

        raise DynslamError(f"unknown synthetic preset '{preset}'; presets: {', '.join(PRESETS)}")
    return Scene(bank.array(), room, statics, movers, camera)


def _kidnap(bank, rng, duration, first_id) -> list[Mover]:
    """A box sits still, a walker picks it up, carries it away, sets it down and leaves."""
    T = duration
    half = np.array([0.22, 0.17, 0.16])
    a = np.array([rng.uniform(-0.6, -0.3), rng.uniform(0.7, 1.0)])
    yaw_a = rng.uniform(-0.4, 0.4)
    start = np.array([-2.2, rng.uniform(-0.95, -0.75)])
    d1 = (a - start) / np.linalg.norm(a - start)
    stand_a = a - 0.42 * d1
    b_target = np.array([rng.uniform(0.4, 0.8), rng.uniform(0.8, 1.1)])
    d2 = (b_target - stand_a) / np.linalg.norm(b_target - stand_a)
    stand_b = b_target - 0.42 * d2
    leave = np.array([2.1, rng.uniform(-0.2, 0.4)])
    legs = [
        (0.05 * T, 0.33 * T, Path2D([start, stand_a], smooth=0)),
        (0.45 * T, 0.68 * T, Path2D([stand_a, stand_b], smooth=0)),
        (0.8 * T, 1.05 * T, Path2D([stand_b, (stand_b + leave) / 2 + [0, 0.3], leave], smooth=2)),
    ]
    itin = Itinerary(legs)

    def ramp(t, t0, t1):
        return smoothstep((t - t0) / (t1 - t0))

    def carry(t):
        return ramp(t, 0.34 * T, 0.4 * T) * (1 - ramp(t, 0.72 * T, 0.78 * T))

    def bend(t):
        return max(ramp(t, 0.34 * T, 0.38 * T) * (1 - ramp(t, 0.4 * T, 0.44 * T)),
                   ramp(t, 0.69 * T, 0.73 * T) * (1 - ramp(t, 0.75 * T, 0.79 * T)))

    walker = Walker(bank, rng, itin, carry=carry, bend=bend)
    box_tex = bank.add(tx.cardboard(rng))

    def floor_pose(pos2, yaw):
        return np.array([pos2[0], pos2[1], half[2]]), yaw

    def carried_pose(t):
        pos, head, _ = itin(t)
        fwd = np.array([np.cos(head), np.sin(head), 0.0])
        return np.array([pos[0], pos[1], 0.95 * walker.k]) + (0.2 + half[0]) * fwd, head

    off = yaw_a - itin(0.38 * T)[1]
    t_pick0, t_pick1 = 0.36 * T, 0.42 * T
    t_put0, t_put1 = 0.7 * T, 0.76 * T

    def box_at(t: float) -> Parts:
        if t < t_pick0:
            c, yaw = floor_pose(a, yaw_a)
        elif t < t_pick1:
            w = ramp(t, t_pick0, t_pick1)
            c0, y0 = floor_pose(a, yaw_a)
            c1, h1 = carried_pose(t)
            c, yaw = (1 - w) * c0 + w * c1, (1 - w) * y0 + w * (h1 + off)
        elif t < t_put0:
            c, h = carried_pose(t)
            yaw = h + off
        else:
            cb, hb = carried_pose(t_put0)
            final = np.array([cb[0], cb[1], half[2]])
            w = ramp(t, t_put0, t_put1)
            c, yaw = (1 - w) * cb + w * final, hb + off
        return Parts().box(c, half, rot_z(yaw), box_tex, 0.5)

    return [Mover("box", first_id, box_at), Mover("walker", first_id + 1, walker.at)]


def _balloon(bank, rng, camera, duration, fps, obj_id) -> Mover:
    """A ball thrown in from beside the camera, bouncing in front of it, batted again now and then."""
    radius = rng.uniform(0.17, 0.22)
    tex = bank.add(tx.ball(rng))
    lo = np.array([-1.2, 0.0, radius])
    hi = np.array([1.2, 1.2, 2.0])
    g = np.array([0.0, 0.0, -4.0])  # a light ball: weak effective gravity (drag)
    t_launch = 0.1 * duration
    R0, c0 = camera(t_launch)
    # Thrown in by someone standing left of the camera, out of its view.
    p = c0 + R0 @ np.array([-0.9, 0.1, 0.7])
    p = np.clip(p, ROOM_MIN + radius + 0.05, ROOM_MAX - radius - 0.05)

    def aim(pos, flight):
        target = np.array([rng.uniform(-0.9, 0.9), rng.uniform(0.4, 1.2), rng.uniform(0.8, 1.6)])
        return (target - pos) / flight - 0.5 * g * flight

    sub = 8
    dt = 1.0 / (fps * sub)
    n = int(np.ceil(duration * fps)) + 2
    pos = np.zeros((n, 3))
    rot = np.zeros((n, 3, 3))
    R = np.eye(3)
    v = np.zeros(3)
    launched = False
    next_kick = None
    for i in range(n):
        pos[i], rot[i] = p, R
        for s in range(sub):
            t = (i * sub + s) * dt
            if not launched:
                if t >= t_launch:
                    launched = True
                    v = aim(p, 0.5)
                    next_kick = t + rng.uniform(1.2, 2.0)
                continue
            if t >= next_kick:
                v = aim(p, rng.uniform(0.6, 0.9))
                next_kick = t + rng.uniform(1.2, 2.0)
            v = v + g * dt
            v *= 1.0 - 0.3 * dt
            p = p + v * dt
            for k in range(3):  # bounce off the play region's bounds (the floor included)
                if (p[k] < lo[k] and v[k] < 0) or (p[k] > hi[k] and v[k] > 0):
                    v[k] = -0.8 * v[k]
            speed = np.linalg.norm(v[:2])
            if speed > 1e-6:
                axis = np.array([-v[1], v[0], 0.0]) / speed
                ang = speed * dt / radius
                K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
                R = (np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K) @ R
                u_, _, vt = np.linalg.svd(R)
                R = u_ @ vt

    def at(t: float) -> Parts:
        i = int(round(t * fps))
        i = min(max(i, 0), n - 1)
        return Parts().ellipsoid(pos[i], (radius, radius, radius), rot[i], tex, 2 * np.pi * radius)

    return Mover("ball", obj_id, at)
