"""The encoder protocol, batched masked instance crops."""

from __future__ import annotations

from typing import Protocol, Sequence

import cv2
import numpy as np

from dynslam_cli.errors import DynslamError

# Instance crops: a margin around each instance's bounding box (fraction of its size), pixels outside the instance
# grey (the normalisation mean; 'zero' = black), and crops per encoder batch.
CROP_MARGIN = 0.1
CROP_BACKGROUND = "grey"
ENCODER_BATCH = 32

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)


class Encoder(Protocol):
    name: str
    dim: int
    backend: str  # what computes the embeddings (run.json names it: runtimes round differently)

    def encode(self, rgb: np.ndarray, ids_or_masks: np.ndarray) -> np.ndarray:
        """(K, D) float32 L2-normalised embeddings of the instances (ids 1..K of an H×W id map, or
        K H×W bool masks)."""
        ...


def as_masks(ids_or_masks: np.ndarray) -> list[np.ndarray]:
    """K bool masks from an id map (ids 1..K) or a (K, H, W) mask stack."""
    a = np.asarray(ids_or_masks)
    if a.ndim == 3:
        return [a[k].astype(bool) for k in range(a.shape[0])]
    if a.ndim == 2:
        return [a == k for k in range(1, int(a.max(initial=0)) + 1)]
    raise DynslamError(f"instances must be an H×W id map or K×H×W masks, got shape {a.shape}")


def instance_boxes(ids: np.ndarray, k: int) -> np.ndarray:
    """(k, 4) x0, y0, x1, y1 (exclusive) bounding boxes of ids 1..k; empty ids give zeros."""
    from scipy.ndimage import find_objects

    boxes = np.zeros((k, 4), np.int64)
    if k == 0:
        return boxes
    for i, sl in enumerate(find_objects(np.asarray(ids), max_label=k)):
        if sl is not None:
            boxes[i] = sl[1].start, sl[0].start, sl[1].stop, sl[0].stop
    return boxes


def masked_crops(rgb: np.ndarray, ids_or_masks: np.ndarray, size: int, margin: float = 0.1,
                 fill: Sequence[int] = (124, 116, 104)) -> np.ndarray:
    """(K, size, size, 3) uint8 crops: each instance's bounding box grown by ``margin``, made
    square (so the aspect is kept), pixels outside the instance set to ``fill``, resized."""
    a = np.asarray(ids_or_masks)
    if a.ndim == 3:
        k = a.shape[0]
        ids = np.zeros(a.shape[1:], np.int32)
        for i in range(k):  # for boxes only; each crop uses its own mask below
            ids[a[i]] = i + 1
        boxes = np.array([_mask_box(a[i]) for i in range(k)], np.int64).reshape(k, 4)
        get = lambda i, sl: a[i][sl]  # noqa: E731
    else:
        k = int(a.max(initial=0))
        boxes = instance_boxes(a, k)
        get = lambda i, sl: a[sl] == i + 1  # noqa: E731
    h, w = rgb.shape[:2]
    out = np.empty((k, size, size, 3), np.uint8)
    fill_arr = np.array(fill, np.uint8)
    for i in range(k):
        x0, y0, x1, y1 = boxes[i]
        if x1 <= x0 or y1 <= y0:
            out[i] = fill_arr
            continue
        bw, bh = x1 - x0, y1 - y0
        side = int(np.ceil(max(bw, bh) * (1.0 + 2.0 * margin)))
        cx, cy = (x0 + x1) / 2.0, (y0 + y1) / 2.0
        sx0, sy0 = int(np.floor(cx - side / 2.0)), int(np.floor(cy - side / 2.0))
        canvas = np.empty((side, side, 3), np.uint8)
        canvas[:] = fill_arr
        ix0, iy0 = max(sx0, 0), max(sy0, 0)
        ix1, iy1 = min(sx0 + side, w), min(sy0 + side, h)
        sl = (slice(iy0, iy1), slice(ix0, ix1))
        m = get(i, sl)
        patch = canvas[iy0 - sy0:iy1 - sy0, ix0 - sx0:ix1 - sx0]
        np.copyto(patch, rgb[sl], where=np.asarray(m, bool)[..., None])
        interp = cv2.INTER_AREA if side > size else cv2.INTER_LINEAR
        out[i] = cv2.resize(canvas, (size, size), interpolation=interp)
    return out


def _mask_box(m: np.ndarray) -> tuple[int, int, int, int]:
    ys, xs = np.nonzero(m)
    if len(xs) == 0:
        return 0, 0, 0, 0
    return int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1


def normalise_batch(crops: np.ndarray, mean: Sequence[float], std: Sequence[float]) -> np.ndarray:
    """(K, S, S, 3) uint8 → (K, 3, S, S) float32 ((x/255 − mean)/std), through a 256-entry table
    per channel computed with the same float32 operations."""
    v = np.arange(256, dtype=np.float32) / 255.0
    lut = (v[:, None] - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)  # (256, 3)
    c = np.asarray(crops)
    out = np.empty((c.shape[0], 3, c.shape[1], c.shape[2]), np.float32)
    for ch in range(3):
        np.take(lut[:, ch], c[..., ch], out=out[:, ch])
    return out


def l2n(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float32)
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)


def crop_fill(mean: Sequence[float], mode: str) -> tuple[int, int, int]:
    if mode == "zero":
        return (0, 0, 0)
    if mode != "grey":
        raise DynslamError(f"crop background must be grey or zero, got '{mode}'")
    return tuple(int(round(255 * m)) for m in mean)  # type: ignore[return-value]
