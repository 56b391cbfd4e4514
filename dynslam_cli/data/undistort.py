"""Undistortion of RGB-D frames with OpenCV remap, keeping the same camera matrix.

The colour image is resampled bilinearly; depth (and label images) with nearest neighbour so
that every output depth is one of the measured values or 0 (outside the image): no depth is
ever interpolated across an object boundary.
"""

from __future__ import annotations

from collections.abc import Sequence as Seq

import numpy as np


def has_distortion(distortion: Seq[float] | None) -> bool:
    return distortion is not None and any(abs(float(d)) > 0.0 for d in distortion)


class Undistorter:
    """Precomputed remap tables for images of ``width`` × ``height`` with camera matrix ``K``."""

    def __init__(self, K: np.ndarray, distortion: Seq[float], width: int, height: int):
        import cv2

        self.K = np.asarray(K, dtype=np.float64)
        self.distortion = np.asarray(list(distortion), dtype=np.float64)
        self.size = (int(width), int(height))
        self.map_x, self.map_y = cv2.initUndistortRectifyMap(
            self.K, self.distortion, None, self.K, self.size, cv2.CV_32FC1)

    def _check(self, image: np.ndarray) -> None:
        if image.shape[1] != self.size[0] or image.shape[0] != self.size[1]:
            raise ValueError(f"image of {image.shape[1]}x{image.shape[0]} given to an undistorter "
                             f"made for {self.size[0]}x{self.size[1]}")

    def rgb(self, image: np.ndarray) -> np.ndarray:
        """Bilinear resampling (colour images); pixels from outside the image become 0."""
        import cv2

        self._check(image)
        return cv2.remap(image, self.map_x, self.map_y, interpolation=cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def nearest(self, image: np.ndarray) -> np.ndarray:
        """Nearest-neighbour resampling (depth, instance ids, masks); outside = 0."""
        import cv2

        self._check(image)
        src = image.view(np.uint8) if image.dtype == np.bool_ else image
        if src.dtype == np.int32:  # remap supports int32 only through float32 here; ids < 2^24
            out = cv2.remap(src.astype(np.float32), self.map_x, self.map_y,
                            interpolation=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                            borderValue=0).astype(np.int32)
        else:
            out = cv2.remap(src, self.map_x, self.map_y, interpolation=cv2.INTER_NEAREST,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return out.astype(np.bool_) if image.dtype == np.bool_ else out

    depth = nearest
