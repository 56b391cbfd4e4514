"""RGB-D sensor model: Kinect-like depth noise, holes and quantisation; colour noise."""

from __future__ import annotations

import numpy as np

DEPTH_SCALE = 5000.0
MIN_DEPTH = 0.25  # metres; closer surfaces read as holes like a structured-light sensor
MAX_DEPTH = 12.0


def edge_hole_mask(depth: np.ndarray, fx: float = 525.0) -> np.ndarray:
    """Pixels on the far side of a depth discontinuity (shadow of the nearer surface).

    A jump counts when it exceeds what a surface seen at up to ~80 degrees produces between
    neighbouring pixels (5 d / fx), plus a margin, so slanted floors are not cut at low resolution.
    """
    d = depth
    thresh = 0.03 + 0.02 * d + 5.0 * d / fx
    mask = np.zeros(d.shape, bool)
    # Compare with the 4 neighbours: this pixel is farther than a neighbour by more than thresh.
    mask[:, 1:] |= (d[:, 1:] - d[:, :-1]) > thresh[:, 1:]
    mask[:, :-1] |= (d[:, :-1] - d[:, 1:]) > thresh[:, :-1]
    mask[1:, :] |= (d[1:, :] - d[:-1, :]) > thresh[1:, :]
    mask[:-1, :] |= (d[:-1, :] - d[1:, :]) > thresh[:-1, :]
    return mask


def sense_depth(depth: np.ndarray, rng: np.random.Generator, noise_at_1m: float, hole_fraction: float,
                edge_holes: bool, fx: float = 525.0) -> np.ndarray:
    """Ground-truth z-depth (metres, 0 = nothing) -> uint16 sensor depth (metres x 5000, 0 = hole)."""
    noisy = depth + rng.standard_normal(depth.shape) * (noise_at_1m * depth * depth)
    holes = (depth <= MIN_DEPTH) | (depth >= MAX_DEPTH)
    if hole_fraction > 0:
        holes |= rng.random(depth.shape) < hole_fraction
    if edge_holes:
        edge = edge_hole_mask(depth, fx)
        # Widen the shadow by a pixel here and there, as real sensors do.
        grow = np.zeros_like(edge)
        grow[:, 1:] |= edge[:, :-1]
        grow[:, :-1] |= edge[:, 1:]
        holes |= edge | (grow & (rng.random(depth.shape) < 0.5))
    q = np.round(np.clip(noisy, 0.0, 65535 / DEPTH_SCALE) * DEPTH_SCALE)
    q[holes] = 0
    return q.astype(np.uint16)


def sense_rgb(rgb: np.ndarray, rng: np.random.Generator, noise: float) -> np.ndarray:
    """Float RGB (0..255) -> uint8 with Gaussian colour noise."""
    if noise > 0:
        rgb = rgb + rng.standard_normal(rgb.shape, dtype=np.float32) * np.float32(noise)
    return np.clip(np.round(rgb), 0, 255).astype(np.uint8)
