"""Weightless baseline encoder: an HSV colour histogram of each instance's pixels."""

from __future__ import annotations

import cv2
import numpy as np

from dynslam_cli.motion.encode_base import as_masks, l2n


class ColorHistEncoder:
    """Joint H×S×V histogram (8×4×4 bins by default) of the masked pixels, square-rooted and
    L2-normalised (Hellinger embedding)."""

    name = "color-hist"
    backend = "numpy"

    def __init__(self, bins: tuple[int, int, int] = (8, 4, 4)):
        self.bins = tuple(int(b) for b in bins)
        self.dim = int(np.prod(self.bins))

    def _codes(self, rgb: np.ndarray) -> np.ndarray:
        hsv = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2HSV)  # H 0..179, S, V 0..255
        bh, bs, bv = self.bins
        h = np.minimum(hsv[..., 0].astype(np.int32) * bh // 180, bh - 1)
        s = np.minimum(hsv[..., 1].astype(np.int32) * bs // 256, bs - 1)
        v = np.minimum(hsv[..., 2].astype(np.int32) * bv // 256, bv - 1)
        return (h * bs + s) * bv + v

    def encode(self, rgb: np.ndarray, ids_or_masks: np.ndarray) -> np.ndarray:
        codes = self._codes(rgb)
        a = np.asarray(ids_or_masks)
        if a.ndim == 2:
            k = int(a.max(initial=0))
            m = a > 0
            flat = (a[m].astype(np.int64) - 1) * self.dim + codes[m]
            hist = np.bincount(flat, minlength=k * self.dim).reshape(k, self.dim).astype(np.float32)
        else:
            masks = as_masks(a)
            hist = np.stack([np.bincount(codes[mk], minlength=self.dim) for mk in masks]).astype(np.float32) \
                if masks else np.zeros((0, self.dim), np.float32)
        hist /= np.maximum(hist.sum(1, keepdims=True), 1.0)
        return l2n(np.sqrt(hist))
