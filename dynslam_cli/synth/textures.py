"""Procedural textures (uint8 RGB, square, tileable) for the synthetic scenes.

Every surface gets trackable texture at several scales: multi-octave value noise as the base,
plus structure per material (tiles, planks, posters, stripes).  All randomness comes from the
generator passed in, so a seed fixes every texel.
"""

from __future__ import annotations

import cv2
import numpy as np

SIZE = 512  # texels per side of every texture


def value_noise(rng: np.random.Generator, size: int, octaves: tuple[int, ...] = (4, 8, 16, 32, 64, 128),
                persistence: float = 0.6) -> np.ndarray:
    """Tileable multi-octave value noise in [0, 1] (size x size float32)."""
    out = np.zeros((size, size), np.float32)
    amp, total = 1.0, 0.0
    for cells in octaves:
        grid = rng.random((cells, cells)).astype(np.float32)
        # Pad by wrapping, upsample, crop: the result tiles seamlessly.
        pad = 2
        step = -(-size // cells)  # ceil: exact tiling when cells divides size
        big = cv2.resize(np.pad(grid, pad, mode="wrap"), ((cells + 2 * pad) * step, (cells + 2 * pad) * step),
                         interpolation=cv2.INTER_CUBIC)
        up = big[pad * step:pad * step + size, pad * step:pad * step + size]
        out += amp * up
        total += amp
        amp *= persistence
    out /= total
    lo, hi = np.percentile(out, (1, 99))
    return np.clip((out - lo) / max(hi - lo, 1e-6), 0.0, 1.0)


def _tint(gray: np.ndarray, c0, c1) -> np.ndarray:
    c0 = np.asarray(c0, np.float32)
    c1 = np.asarray(c1, np.float32)
    return gray[..., None] * (c1 - c0) + c0


def _rand_colour(rng: np.random.Generator, sat: float = 0.6, lo: float = 60, hi: float = 230) -> np.ndarray:
    hue = rng.random()
    base = np.array([np.cos(2 * np.pi * (hue + k / 3)) for k in range(3)], np.float32)
    val = lo + (hi - lo) * rng.random()
    return np.clip(val * (1 - sat + sat * (0.5 + 0.5 * base)), 0, 255)


def _finish(img: np.ndarray) -> np.ndarray:
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def wall(rng: np.random.Generator, size: int = SIZE, posters: int = 3) -> np.ndarray:
    """Painted plaster with noise, a skirting stripe and a few posters."""
    base = _rand_colour(rng, sat=0.25, lo=150, hi=220)
    # Strong fine octaves: plaster grain that stays trackable close up.
    n = value_noise(rng, size, octaves=(4, 8, 16, 32, 64, 128, 256), persistence=0.8)
    img = _tint(n, base * 0.7, np.minimum(base * 1.15, 255))
    for _ in range(posters):
        w = int(size * rng.uniform(0.15, 0.3))
        h = int(w * rng.uniform(0.9, 1.5))
        x0 = int(rng.integers(0, size - w))
        y0 = int(rng.integers(0, size - h))
        img[y0:y0 + h, x0:x0 + w] = poster(rng, w, h)
    return _finish(img)


def poster(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """A framed picture: coloured blobs, bars and circles on a noisy background."""
    c0, c1 = _rand_colour(rng), _rand_colour(rng)
    img = _tint(value_noise(rng, max(w, h), octaves=(2, 4, 8, 16))[:h, :w], c0, c1)
    img = np.ascontiguousarray(img)
    for _ in range(int(rng.integers(4, 10))):
        col = tuple(float(v) for v in _rand_colour(rng, sat=0.9, lo=20, hi=255))
        kind = rng.integers(0, 3)
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        if kind == 0:
            cv2.circle(img, (x, y), int(rng.integers(3, max(4, w // 4))), col, -1, cv2.LINE_AA)
        elif kind == 1:
            x2, y2 = int(rng.integers(0, w)), int(rng.integers(0, h))
            cv2.rectangle(img, (x, y), (x2, y2), col, -1)
        else:
            x2, y2 = int(rng.integers(0, w)), int(rng.integers(0, h))
            cv2.line(img, (x, y), (x2, y2), col, int(rng.integers(1, 4)), cv2.LINE_AA)
    t = max(2, w // 30)
    img[:t], img[-t:], img[:, :t], img[:, -t:] = 30, 30, 30, 30
    return img


def tiles(rng: np.random.Generator, size: int = SIZE, n: int = 4) -> np.ndarray:
    """Floor tiles: n x n tiles with grout lines, each tile its own shade, noise on top."""
    c0 = _rand_colour(rng, sat=0.3, lo=90, hi=200)
    img = _tint(value_noise(rng, size), c0 * 0.75, np.minimum(c0 * 1.2, 255))
    step = size // n
    for i in range(n):
        for j in range(n):
            img[i * step:(i + 1) * step, j * step:(j + 1) * step] *= rng.uniform(0.8, 1.15)
    g = max(2, size // 128)
    for k in range(n):
        img[k * step:k * step + g] = 60
        img[:, k * step:k * step + g] = 60
    return _finish(img)


def planks(rng: np.random.Generator, size: int = SIZE, n: int = 6) -> np.ndarray:
    """Wood: stretched noise grain in n planks with dark seams and per-plank shade."""
    c0 = np.array([60, 90, 140], np.float32) * rng.uniform(0.8, 1.2)  # BGR-ish brown, stored RGB below
    c0 = c0[::-1]
    grain = value_noise(rng, size, octaves=(4, 8, 32, 64, 128))
    grain = cv2.resize(grain[:, : size // 8], (size, size), interpolation=cv2.INTER_LINEAR)
    fine = value_noise(rng, size, octaves=(16, 64, 128))
    img = _tint(0.7 * grain + 0.3 * fine, c0 * 0.65, np.minimum(c0 * 1.35, 255))
    step = size // n
    for k in range(n):
        img[k * step:(k + 1) * step] *= rng.uniform(0.85, 1.15)
        img[k * step:k * step + 2] = 40
    return _finish(img)


def ceiling(rng: np.random.Generator, size: int = SIZE) -> np.ndarray:
    """Ceiling panels: light panels with grid lines, speckle noise and a few lamps."""
    img = _tint(value_noise(rng, size, octaves=(8, 32, 64, 128)), (150, 150, 145), (235, 235, 230))
    step = size // 4
    for k in range(4):
        img[k * step:k * step + 3] = 90
        img[:, k * step:k * step + 3] = 90
    for _ in range(3):
        i, j = rng.integers(0, 4, size=2)
        img[i * step + 20:(i + 1) * step - 20, j * step + 20:(j + 1) * step - 20] = 250
    return _finish(img)


def fabric(rng: np.random.Generator, size: int = SIZE) -> np.ndarray:
    """Clothes: stripes or checks in two colours over noise."""
    c0, c1 = _rand_colour(rng, sat=0.7, lo=40, hi=200), _rand_colour(rng, sat=0.7, lo=40, hi=230)
    n = value_noise(rng, size, octaves=(8, 16, 64, 128))
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    period = size / float(rng.integers(6, 14))
    if rng.random() < 0.5:
        pattern = (np.sin(2 * np.pi * yy / period) > 0).astype(np.float32)
    else:
        pattern = ((np.sin(2 * np.pi * yy / period) > 0) ^ (np.sin(2 * np.pi * xx / period) > 0)).astype(np.float32)
    img = _tint(pattern, c0, c1) * (0.75 + 0.5 * n[..., None])
    return _finish(img)


def skin(rng: np.random.Generator, size: int = SIZE) -> np.ndarray:
    base = np.array([210, 160, 130], np.float32) * rng.uniform(0.55, 1.05)
    img = _tint(value_noise(rng, size, octaves=(4, 16, 64, 128), persistence=0.75), base * 0.8,
                np.minimum(base * 1.15, 255))
    # A darker band (hair / eyes region) so that the head rotation is visible.
    img[: size // 3] *= 0.45
    return _finish(img)


def painted(rng: np.random.Generator, size: int = SIZE) -> np.ndarray:
    """Painted/laminated furniture: a plain colour with noise, scratches and labels."""
    c = _rand_colour(rng, sat=0.5, lo=70, hi=220)
    img = np.ascontiguousarray(_tint(value_noise(rng, size, persistence=0.75), c * 0.6, np.minimum(c * 1.25, 255)))
    for _ in range(int(rng.integers(6, 14))):
        x, y = int(rng.integers(0, size)), int(rng.integers(0, size))
        w, h = int(rng.integers(8, size // 5)), int(rng.integers(8, size // 5))
        col = tuple(float(v) for v in _rand_colour(rng, sat=0.8, lo=10, hi=255))
        cv2.rectangle(img, (x, y), (x + w, y + h), col, -1)
    return _finish(img)


def ball(rng: np.random.Generator, size: int = SIZE) -> np.ndarray:
    """Beach-ball segments: 6 coloured sectors (by longitude) with noise."""
    cols = [_rand_colour(rng, sat=0.9, lo=120, hi=255) for _ in range(6)]
    xx = np.arange(size)[None, :].repeat(size, 0)
    seg = (xx * 6) // size
    img = np.stack(cols)[seg]
    img *= (0.8 + 0.4 * value_noise(rng, size, octaves=(8, 32, 64)))[..., None]
    return _finish(img)


def cardboard(rng: np.random.Generator, size: int = SIZE) -> np.ndarray:
    base = np.array([190, 150, 100], np.float32) * rng.uniform(0.85, 1.1)
    img = _finish(_tint(value_noise(rng, size), base * 0.7, np.minimum(base * 1.2, 255)))
    cv2.rectangle(img, (0, size // 2 - 12), (size, size // 2 + 12), (200, 190, 160), -1)
    for _ in range(5):
        x, y = int(rng.integers(0, size - 60)), int(rng.integers(0, size - 60))
        cv2.putText(img, "FRAGILE" if rng.random() < 0.5 else "THIS SIDE UP", (x, y + 40),
                    cv2.FONT_HERSHEY_SIMPLEX, 1.2, (40, 30, 120), 3, cv2.LINE_AA)
    return img


class TextureBank:
    """Collects textures and hands out their index; ``array()`` stacks them (T, S, S, 3)."""

    def __init__(self) -> None:
        self._items: list[np.ndarray] = []

    def add(self, img: np.ndarray) -> int:
        if img.shape != (SIZE, SIZE, 3):
            img = cv2.resize(img, (SIZE, SIZE), interpolation=cv2.INTER_AREA)
        self._items.append(np.ascontiguousarray(img, dtype=np.uint8))
        return len(self._items) - 1

    def array(self) -> np.ndarray:
        return np.stack(self._items)
