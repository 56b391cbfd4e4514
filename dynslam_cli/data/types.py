"""Plain data types of the data layer: camera intrinsics and one RGB-D frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels for an image of ``width`` × ``height``."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        """The 3×3 camera matrix (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]],
                        dtype=np.float64)

    def scaled(self, factor: float) -> Intrinsics:
        """Intrinsics of the image resized by ``factor`` (pixel-centre convention).

        A pixel centre ``u`` maps to ``(u + 0.5) * factor - 0.5``; focal lengths scale by
        ``factor``; the size is rounded to whole pixels.
        """
        if factor <= 0:
            raise ValueError(f"scale factor must be positive, got {factor}")
        return Intrinsics(
            fx=self.fx * factor, fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5, cy=(self.cy + 0.5) * factor - 0.5,
            width=round(self.width * factor), height=round(self.height * factor),
        )

    def as_list(self) -> list[float]:
        """``[fx, fy, cx, cy]`` (the config's order)."""
        return [self.fx, self.fy, self.cx, self.cy]


@dataclass
class Frame:
    """One RGB-D frame of a (cut) sequence; see DEVELOPING.md, "Data contracts"."""

    index: int  # position in the cut sequence
    timestamp: float  # seconds (the rgb image's timestamp)
    rgb: np.ndarray  # H×W×3 uint8, RGB order
    depth: np.ndarray  # H×W float32 metres, 0 = invalid
    pose_c2w: np.ndarray | None = None  # 4×4 float64 ground truth (evaluation only) or None
    instance_ids: np.ndarray | None = None  # H×W int32, 0 = background (synthetic scenes)
    dynamic_mask: np.ndarray | None = None  # H×W bool, True = moving (synthetic scenes)
    depth_full: np.ndarray | None = None  # H×W float32 metres before data.max_depth; None = same as depth

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])
