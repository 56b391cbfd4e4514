"""Small geometry helpers of the synthetic scenes: rotations, camera frames, primitives, paths."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

UP = np.array([0.0, 0.0, 1.0])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def frame_from_z(d: np.ndarray) -> np.ndarray:
    """A rotation whose local z axis is the unit vector ``d`` (columns: local axes in world)."""
    z = d / (np.linalg.norm(d) + 1e-12)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def camera_rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Camera-to-world rotation (OpenCV optical: x right, y down, z forward) in a z-up world.

    yaw: heading of the optical axis about world z (0 = looking along +x); pitch: up positive;
    roll: about the optical axis.
    """
    f = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    r = np.cross(f, UP)
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    c, s = np.cos(roll), np.sin(roll)
    r2 = c * r + s * d
    d2 = -s * r + c * d
    return np.stack([r2, d2, f], axis=1)


def look_at(eye: np.ndarray, target: np.ndarray, roll: float = 0.0) -> np.ndarray:
    f = np.asarray(target, float) - np.asarray(eye, float)
    yaw = float(np.arctan2(f[1], f[0]))
    pitch = float(np.arctan2(f[2], np.hypot(f[0], f[1])))
    return camera_rotation(yaw, pitch, roll)


def rot_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (qx, qy, qz, qw) of a rotation matrix, qw >= 0 (the TUM writer's convention)."""
    from dynslam_cli.data.tum import matrix_to_quat

    return matrix_to_quat(R)


@dataclass
class Parts:
    """Primitives of one object at one instant (boxes and ellipsoids), all with the same id."""

    box_c: list = field(default_factory=list)
    box_R: list = field(default_factory=list)
    box_h: list = field(default_factory=list)
    box_tex: list = field(default_factory=list)  # 6 texture ids per box (-x,+x,-y,+y,-z,+z)
    box_scale: list = field(default_factory=list)
    ell_c: list = field(default_factory=list)
    ell_R: list = field(default_factory=list)
    ell_r: list = field(default_factory=list)
    ell_tex: list = field(default_factory=list)
    ell_scale: list = field(default_factory=list)

    def box(self, centre, half, R=None, tex=0, scale=1.0) -> "Parts":
        self.box_c.append(np.asarray(centre, float))
        self.box_R.append(np.eye(3) if R is None else np.asarray(R, float))
        self.box_h.append(np.asarray(half, float))
        self.box_tex.append([tex] * 6 if np.isscalar(tex) else list(tex))
        self.box_scale.append(float(scale))
        return self

    def ellipsoid(self, centre, radii, R=None, tex=0, scale=1.0) -> "Parts":
        self.ell_c.append(np.asarray(centre, float))
        self.ell_R.append(np.eye(3) if R is None else np.asarray(R, float))
        self.ell_r.append(np.asarray(radii, float))
        self.ell_tex.append(int(tex))
        self.ell_scale.append(float(scale))
        return self

    def segment(self, p, q, radius, tex=0, scale=1.0) -> "Parts":
        """A capsule-like ellipsoid from p to q (long axis along the segment)."""
        p, q = np.asarray(p, float), np.asarray(q, float)
        d = q - p
        length = float(np.linalg.norm(d))
        return self.ellipsoid((p + q) / 2, (radius, radius, length / 2 + 0.6 * radius), frame_from_z(d), tex, scale)

    def markers(self) -> np.ndarray:
        """Points that move rigidly with the primitives (for motion tests): centres + axis tips."""
        pts = []
        for c, R, h in zip(self.box_c, self.box_R, self.box_h, strict=True):
            pts.append(c)
            pts.extend(c + R[:, k] * h[k] for k in range(3))
        for c, R, r in zip(self.ell_c, self.ell_R, self.ell_r, strict=True):
            pts.append(c)
            pts.extend(c + R[:, k] * r[k] for k in range(3))
        return np.array(pts).reshape(-1, 3)

    def aabb(self) -> np.ndarray:
        """World axis-aligned bounding box [[xmin,ymin,zmin],[xmax,ymax,zmax]]."""
        lo, hi = [], []
        for c, R, h in zip(self.box_c, self.box_R, self.box_h, strict=True):
            ext = np.abs(R) @ h
            lo.append(c - ext)
            hi.append(c + ext)
        for c, R, r in zip(self.ell_c, self.ell_R, self.ell_r, strict=True):
            ext = np.sqrt((R * r[None, :]) ** 2 @ np.ones(3))
            lo.append(c - ext)
            hi.append(c + ext)
        return np.array([np.min(lo, axis=0), np.max(hi, axis=0)])

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        box = self.aabb()
        centre = box.mean(axis=0)
        return centre, float(np.linalg.norm(box[1] - box[0]) / 2 + 1e-3)


class Path2D:
    """A smooth path on the floor (Chaikin-smoothed polyline), parameterised by arc length."""

    def __init__(self, points, closed: bool = False, smooth: int = 3):
        pts = np.asarray(points, float)
        for _ in range(smooth):
            pts = _chaikin(pts, closed)
        if closed:
            pts = np.vstack([pts, pts[:1]])
        self.closed = closed
        self.pts = pts
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        self.s = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(self.s[-1])

    def at(self, s: float) -> tuple[np.ndarray, float]:
        """Position (2,) and heading (rad) at arc length s (wrapping when closed, clamped else)."""
        if self.closed:
            s = s % self.length
        s = float(np.clip(s, 0.0, self.length))
        k = int(np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self.s) - 2))
        seg = self.s[k + 1] - self.s[k]
        w = 0.0 if seg <= 0 else (s - self.s[k]) / seg
        p = self.pts[k] * (1 - w) + self.pts[k + 1] * w
        d = self.pts[k + 1] - self.pts[k]
        # Heading: blend the neighbouring segments' directions for smooth turning.
        k2 = k + 1 if w > 0.5 else k - 1
        if self.closed:
            k2 %= len(self.pts) - 1
        if 0 <= k2 < len(self.pts) - 1:
            d2 = self.pts[k2 + 1] - self.pts[k2]
            a = abs(w - 0.5)
            d = d / (np.linalg.norm(d) + 1e-12) * (1.0 - a) + d2 / (np.linalg.norm(d2) + 1e-12) * a
        return p, float(np.arctan2(d[1], d[0]))


def _chaikin(pts: np.ndarray, closed: bool) -> np.ndarray:
    if closed:
        nxt = np.roll(pts, -1, axis=0)
        q = 0.75 * pts + 0.25 * nxt
        r = 0.25 * pts + 0.75 * nxt
        return np.stack([q, r], axis=1).reshape(-1, 2)
    q = 0.75 * pts[:-1] + 0.25 * pts[1:]
    r = 0.25 * pts[:-1] + 0.75 * pts[1:]
    mid = np.stack([q, r], axis=1).reshape(-1, 2)
    return np.vstack([pts[:1], mid, pts[-1:]])


def smoothstep(x: float) -> float:
    x = float(np.clip(x, 0.0, 1.0))
    return x * x * (3 - 2 * x)
