"""Data passed between the motion parts: segmentations, per-frame instances, update records."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from dynslam_cli.errors import DynslamError


@dataclass
class Segmentation:
    """Instances of one image. ``ids``: H×W int32, 0 = background (pixels in no segment), 1..K the
    instances after pruning; ``class_ids``: (K,) int (-1 where the segmenter has no classes);
    ``scores``: (K,) float32 confidences (1.0 for weightless segmenters); ``extent``: H×W int32 or None,
    each instance grown through continuous depth over the pixels ``ids`` leaves to the nearest segment
    (the geometric segmenter's; None = none)."""

    ids: np.ndarray
    class_ids: np.ndarray
    scores: np.ndarray
    extent: Optional[np.ndarray] = None

    @property
    def count(self) -> int:
        return int(len(self.class_ids))

    @staticmethod
    def empty(h: int, w: int) -> "Segmentation":
        return Segmentation(np.zeros((h, w), np.int32), np.zeros(0, np.int64), np.zeros(0, np.float32))


@dataclass
class Perception:
    """What a frame's pixels alone decide, before its pose and the classifier: the segmentation and
    each instance's embedding (:meth:`MotionModule.perceive`; the run computes it for the next frame
    while the current one is tracked and mapped) and the milliseconds each took."""

    frame_index: int
    seg: Segmentation
    embeddings: np.ndarray  # (K, D) float32, L2-normalised
    timings: dict = field(default_factory=dict)  # segment, encode -> ms


@dataclass
class FrameInstances:
    """What :meth:`MotionModule.observe` returns for a frame.

    ``ids`` H×W int32 (0 = background region, 1..K instances); arrays of length K follow the
    instance order (instance k has id k+1). ``static_mask`` is True on pixels usable for tracking
    and mapping (background and instances classified static)."""

    frame_index: int
    ids: np.ndarray
    embeddings: np.ndarray  # (K, D) float32, L2-normalised
    centres: np.ndarray  # (K, 3) world coordinates (NaN where an instance has no valid depth)
    dynamic: np.ndarray  # (K,) bool
    probs: np.ndarray  # (K,) float32: final probability (max of online and prior under the OR rule)
    static_mask: np.ndarray  # (H, W) bool
    class_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    prior_probs: Optional[np.ndarray] = None  # (K,) from the prior classifier, when configured
    timings: dict = field(default_factory=dict)  # component -> ms
    features: Optional[np.ndarray] = None  # (K, F) the classifier's input (embedding, + centre when configured)
    # (H, W) int32: the segmentation's extent (Segmentation.extent), None where it has none
    grown: Optional[np.ndarray] = None
    # (H, W) int32: what each instance masks when dynamic (ids plus the part of ``grown`` that stands where recent
    # keyframes saw empty space, decided at the tracked pose: MotionModule.bound_outline); None = ids
    extent: Optional[np.ndarray] = None

    @property
    def count(self) -> int:
        return int(self.embeddings.shape[0])

    @property
    def mask_ids(self) -> np.ndarray:
        """H×W int32: the pixels each instance masks when dynamic (``extent``, else ``ids``)."""
        return self.ids if self.extent is None else self.extent

    def dynamic_mask(self) -> np.ndarray:
        """H×W bool: pixels of instances classified dynamic."""
        lut = np.zeros(self.count + 1, bool)
        lut[1:] = self.dynamic
        return lut[self.mask_ids]


@dataclass
class CheckResult:
    """Output of the inconsistency check for one frame (instances 1..K of the frame's id map)."""

    observed_moving: np.ndarray  # (K,) bool: o_k (either direction)
    forward: np.ndarray  # (K,) bool: rendered − observed > t_d on > t_p of the pixels
    backward: np.ndarray  # (K,) bool: via segments of the rendered view where observed − rendered > t_d
    fractions: np.ndarray  # (K,) float: forward inconsistent fraction
    background_forward: float  # fraction over the background region (id 0)
    background_moving: bool  # background flagged (either direction); it stays static for tracking
    rendered_ids: Optional[np.ndarray] = None  # segmentation of the rendered view (check resolution)
    rendered_flagged: Optional[np.ndarray] = None  # ids (in rendered_ids) flagged as 'left'
    judged: Optional[np.ndarray] = None  # (K,) bool: enough valid pixels to be judged


@dataclass
class UpdateRecord:
    """One classifier update (one JSON line of ``classifier_updates.jsonl``)."""

    frame: int
    instances: int  # instances of the current frame used
    labels: list  # o_k per current instance (0/1)
    predicted_before: list  # g's decision before the update per current instance
    contradicted: list  # indices of contradicted instances
    loss_before: float
    loss_after: float
    steps: int
    replay_used: int  # instances drawn from the replay buffer
    replay_size: int  # buffer size after adding this frame's movers
    fixed: bool  # all contradicted labels fixed after the update
    rendered_positives: int = 0  # flagged rendered segments (things that left) encoded from the rendered view

    def to_json(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def intrinsics_tuple(intrinsics) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) from an object with fx/fy/cx/cy, a 3×3 K or a 4-sequence."""
    if intrinsics is None:
        raise DynslamError("motion module needs camera intrinsics")
    if all(hasattr(intrinsics, a) for a in ("fx", "fy", "cx", "cy")):
        return float(intrinsics.fx), float(intrinsics.fy), float(intrinsics.cx), float(intrinsics.cy)
    a = np.asarray(intrinsics, np.float64)
    if a.shape == (3, 3):
        return float(a[0, 0]), float(a[1, 1]), float(a[0, 2]), float(a[1, 2])
    if a.size >= 4:
        a = a.ravel()
        return float(a[0]), float(a[1]), float(a[2]), float(a[3])
    raise DynslamError(f"cannot read intrinsics from {intrinsics!r}")
