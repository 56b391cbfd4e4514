"""Embeddings of instances that did not change since the last frame, reused instead of encoded again.

Consecutive frames show mostly the same segments (the camera moves a few pixels, most of the scene
stands still); encoding each of them again costs the encoder's whole run per frame. An instance of
the current frame takes the embedding of the last frame's instance it overlaps with an IoU of at
least ``REUSE_IOU`` (pixel sets of the two id maps, compared in place: no warping), unless that
embedding has already been carried ``MAX_AGE`` frames since it was computed. Everything else is
encoded. A moving object's segment changes shape and place, so it is encoded again as it moves.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch

# Mask IoU at which two instances of consecutive frames count as the same, unchanged one.
REUSE_IOU = 0.8
# An embedding is reused at most this many frames in a row, then computed again.
MAX_AGE = 4
# The overlap is counted on every STEP-th pixel in each direction.
STEP = 4


def overlap_iou(cur: np.ndarray, k_cur: int, prev: np.ndarray, k_prev: int) -> np.ndarray:
    """(k_cur, k_prev) mask IoU of instances 1..k of two id maps of the same size (0 = none)."""
    if k_cur == 0 or k_prev == 0:
        return np.zeros((k_cur, k_prev), np.float64)
    a = cur.reshape(-1).astype(np.int64)
    b = prev.reshape(-1).astype(np.int64)
    joint = np.bincount(a * (k_prev + 1) + b, minlength=(k_cur + 1) * (k_prev + 1)).reshape(k_cur + 1, k_prev + 1)
    inter = joint[1:, 1:].astype(np.float64)
    area_a = joint[1:, :].sum(1).astype(np.float64)
    area_b = joint[:, 1:].sum(0).astype(np.float64)
    union = area_a[:, None] + area_b[None, :] - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(union > 0, inter / union, 0.0)


class EmbeddingCache:
    """The last frame's instances (subsampled id map), their embeddings and how many frames each
    embedding has been carried."""

    def __init__(self, reuse_iou: float = REUSE_IOU, max_age: int = MAX_AGE, step: int = STEP):
        self.reuse_iou, self.max_age, self.step = float(reuse_iou), int(max_age), int(step)
        self.ids: Optional[np.ndarray] = None
        self.emb: Optional[np.ndarray] = None
        self.age: Optional[np.ndarray] = None

    def encode(self, encoder, rgb: np.ndarray, ids: np.ndarray, k: int) -> tuple[np.ndarray, int]:
        """(k, D) embeddings of instances 1..k of ``ids`` (``encoder.encode`` runs on the ones not
        reused) and how many were encoded."""
        small = np.ascontiguousarray(ids[::self.step, ::self.step])
        src = np.full(k, -1, np.int64)
        if self.ids is not None and self.ids.shape == small.shape and len(self.emb):
            iou = overlap_iou(small, k, self.ids, len(self.emb))
            if iou.size:
                best = iou.argmax(1)
                ok = (iou[np.arange(k), best] >= self.reuse_iou) & (self.age[best] < self.max_age)
                src[ok] = best[ok]
        fresh = np.flatnonzero(src < 0)
        dim = int(encoder.dim)
        emb = np.zeros((k, dim), np.float32)
        age = np.zeros(k, np.int64)
        if len(fresh):
            lut = np.zeros(k + 1, np.int32)
            lut[fresh + 1] = np.arange(1, len(fresh) + 1)
            emb[fresh] = encoder.encode(rgb, lut[ids])
        kept = np.flatnonzero(src >= 0)
        if len(kept):
            emb[kept] = self.emb[src[kept]]
            age[kept] = self.age[src[kept]] + 1
        self.ids, self.emb, self.age = small, emb.copy(), age
        return emb, len(fresh)

    def state_dict(self) -> dict:
        if self.ids is None:
            return {}
        return {"ids": torch.from_numpy(self.ids.astype(np.int32)), "emb": torch.from_numpy(self.emb),
                "age": torch.from_numpy(self.age)}

    def load_state_dict(self, d: dict) -> None:
        if not d:
            self.ids = self.emb = self.age = None
            return
        self.ids = np.asarray(d["ids"].numpy(), np.int32)
        self.emb = np.asarray(d["emb"].numpy(), np.float32)
        self.age = np.asarray(d["age"].numpy(), np.int64)
