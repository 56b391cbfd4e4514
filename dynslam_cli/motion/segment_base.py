"""The segmenter protocol, part-segment pruning and overlap resolution."""

from __future__ import annotations

from typing import Optional, Protocol, Sequence

import numpy as np

from dynslam_cli.motion.types import Segmentation

# Instances with fewer pixels (full resolution) after overlap resolution are dropped to background.
MIN_INSTANCE_AREA = 64
# T_R: drop segment R1 when area(R1 & R2) > T_R * area(R1) for another segment R2.
PRUNE_RATIO = 0.9


class Segmenter(Protocol):
    name: str

    def segment(self, rgb: np.ndarray, depth: Optional[np.ndarray]) -> Segmentation:
        """rgb H×W×3 uint8, depth H×W float32 metres (0 = invalid; may be None for RGB models)."""
        ...


def _overlap_matrix(masks: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairwise intersection areas and areas of (N, H, W) bool masks, measured on a step-subsampled grid."""
    sub = masks[:, ::step, ::step].reshape(len(masks), -1).astype(np.float32)
    inter = sub @ sub.T
    return inter, np.diag(inter).copy()


def prune_parts(masks: np.ndarray, ratio: float = PRUNE_RATIO, step: int = 2,
                order: Optional[np.ndarray] = None) -> np.ndarray:
    """Indices of the masks kept after part-segment pruning (paper, supplementary: T_R = 0.9).

    R1 is dropped when area(R1 ∩ R2) > ratio · area(R1) for another kept segment R2. Segments are
    visited largest first (or in ``order``), so of two near-identical segments the first is kept
    and a part is dropped in favour of the whole it lies in. Empty masks are dropped.
    """
    n = len(masks)
    if n == 0:
        return np.zeros(0, np.int64)
    inter, area = _overlap_matrix(masks, step)
    if order is None:
        order = np.argsort(-area, kind="stable")
    kept: list[int] = []
    for i in order:
        if area[i] <= 0:
            continue
        if kept and np.any(inter[i, kept] > ratio * area[i]):
            continue
        kept.append(int(i))
    return np.array(kept, np.int64)


def masks_to_ids(masks: np.ndarray, min_area: int = 1, order: Optional[Sequence[int]] = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Resolve overlapping masks into an H×W int32 id map (0 = no segment).

    Masks are painted in ``order`` (default: largest first, so smaller segments lying on larger
    ones win the shared pixels); masks left with fewer than ``min_area`` pixels are dropped and the
    rest renumbered 1..K. Returns (ids, source index of each id 1..K).
    """
    n, h, w = masks.shape if len(masks) else (0, 0, 0)
    if n == 0:
        return np.zeros(masks.shape[1:] if masks.ndim == 3 else (0, 0), np.int32), np.zeros(0, np.int64)
    if order is None:
        area = masks.reshape(n, -1).sum(1)
        order = np.argsort(-area, kind="stable")
    canvas = np.zeros((h, w), np.int32)
    for i in order:
        canvas[masks[i]] = int(i) + 1
    counts = np.bincount(canvas.ravel(), minlength=n + 1)
    survivors = [i for i in order if counts[int(i) + 1] >= max(min_area, 1)]
    lut = np.zeros(n + 1, np.int32)
    for new, i in enumerate(survivors, start=1):
        lut[int(i) + 1] = new
    return lut[canvas], np.array(survivors, np.int64)


def relabel(ids: np.ndarray, min_area: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Renumber an id map to 1..K (dropping ids with fewer than ``min_area`` pixels to 0).
    Returns (new ids, old id of each new id 1..K)."""
    counts = np.bincount(ids.ravel())
    old = np.nonzero(counts >= max(min_area, 1))[0]
    old = old[old > 0]
    lut = np.zeros(len(counts), np.int32)
    lut[old] = np.arange(1, len(old) + 1, dtype=np.int32)
    return lut[ids], old
