"""`Sequence`: an indexable, lazily decoded list of RGB-D frames with ground truth.

Readers (``tum.py`` for the TUM layout shared by TUM, Bonn and synthetic folders) build a list of
:class:`FrameRecord` (file names and per-frame ground truth, already associated and cut);
images are decoded only when a frame is requested.  Frame timestamps increase strictly.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dynslam_cli.data.config import DataConfig
from dynslam_cli.data.types import Frame, Intrinsics
from dynslam_cli.errors import DynslamError


@dataclass
class FrameRecord:
    timestamp: float  # rgb timestamp (s)
    rgb: Path
    depth: Path
    pose_c2w: np.ndarray | None = None
    instances: Path | None = None
    dynamic: Path | None = None
    source_index: int = 0  # position among the associated pairs before the cut
    stamp: str = ""  # the rgb timestamp as written in the list file (for output file names)


class Sequence:
    """Frames of one sequence after association and the start/frames/stride cut.

    ``name``, ``dataset`` (tum|bonn|synth), ``path`` (folder), ``spec`` (what the user typed),
    ``intrinsics``, ``distortion`` (the dataset's coefficients, OpenCV order; the frames are
    already undistorted when ``undistorted`` is true), ``timestamps``, ``gt_poses``,
    ``depth_noise`` (the depth's standard deviation per metre²: a synthetic folder's own, else
    ``DataConfig.DEPTH_NOISE``), ``groundtruth_file`` (the raw trajectory file or None) and ``has_gt_masks`` (the folder has
    per-frame motion masks ``dynamic/``; ``has_instances``: instance ids ``instances/``).
    """

    def __init__(self, *, name: str, dataset: str, path: Path, spec: str, intrinsics: Intrinsics,
                 distortion: list[float], records: list[FrameRecord], depth_scale: float,
                 max_depth: float = 0.0, depth_noise: float = DataConfig.DEPTH_NOISE, groundtruth_file: Path | None = None,
                 undistorter=None, has_gt_masks: bool = False, has_instances: bool = False,
                 total_pairs: int | None = None):
        self.name = name
        self.dataset = dataset
        self.path = Path(path)
        self.spec = spec
        self.intrinsics = intrinsics
        self.distortion = list(distortion)
        self.records = records
        self.depth_scale = float(depth_scale)
        self.max_depth = float(max_depth)
        self.depth_noise = float(depth_noise)
        self.groundtruth_file = groundtruth_file
        self._undistorter = undistorter
        self.has_gt_masks = bool(has_gt_masks)
        self.has_instances = bool(has_instances)
        self.total_pairs = len(records) if total_pairs is None else total_pairs
        for k in range(1, len(records)):
            if not records[k].timestamp > records[k - 1].timestamp:
                a, b = records[k - 1], records[k]
                raise DynslamError(
                    f"frames of {dataset}/{name} ({self.path}) are not in time order: frame {k} at "
                    f"{b.stamp or b.timestamp} follows frame {k - 1} at {a.stamp or a.timestamp}")

    # -- sequence protocol -------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, i: int) -> Frame:
        if not isinstance(i, (int, np.integer)):
            raise TypeError(f"frame index must be an integer, got {type(i).__name__}")
        n = len(self.records)
        j = int(i) + n if i < 0 else int(i)
        if not 0 <= j < n:
            raise IndexError(f"frame {i} out of range for {n} frames of {self.name}")
        return self._load(j)

    def __iter__(self) -> Iterator[Frame]:
        for j in range(len(self.records)):
            yield self._load(j)

    def __repr__(self) -> str:
        return (f"Sequence({self.dataset}/{self.name}, {len(self)} frames, "
                f"{self.intrinsics.width}x{self.intrinsics.height}, path={str(self.path)!r})")

    # -- metadata ----------------------------------------------------------------------------
    @property
    def timestamps(self) -> np.ndarray:
        return np.array([r.timestamp for r in self.records], dtype=np.float64)

    @property
    def stamps(self) -> list[str]:
        """The rgb timestamps as written in the input lists (``1305031453.359684``)."""
        return [r.stamp or f"{r.timestamp:.6f}" for r in self.records]

    @property
    def gt_poses(self) -> list[np.ndarray | None]:
        return [None if r.pose_c2w is None else r.pose_c2w.copy() for r in self.records]

    @property
    def undistorted(self) -> bool:
        return self._undistorter is not None

    # -- decoding ----------------------------------------------------------------------------
    def _where(self, j: int) -> str:
        return f"frame {j} of {self.name}"

    def load_rgb(self, j: int) -> np.ndarray:
        import cv2

        rec = self.records[j]
        img = _imread(rec.rgb, cv2.IMREAD_COLOR, self._where(j))
        if img.ndim != 3 or img.shape[2] != 3:
            raise DynslamError(f"colour image {rec.rgb} ({self._where(j)}) is not a 3-channel image")
        self._check_size(img, rec.rgb, j)
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        if self._undistorter is not None:
            img = self._undistorter.rgb(img)
        return np.ascontiguousarray(img)

    def load_depth(self, j: int, cut: bool = True) -> np.ndarray:
        """Depth of frame ``j`` in metres (0 = invalid), undistorted; without ``cut`` also
        beyond ``max_depth``."""
        import cv2

        rec = self.records[j]
        raw = _imread(rec.depth, cv2.IMREAD_UNCHANGED, self._where(j))
        if raw.dtype != np.uint16 or raw.ndim != 2:
            kind = f"{raw.dtype}" + (f" with {raw.shape[2]} channels" if raw.ndim == 3 else "")
            raise DynslamError(f"depth image {rec.depth} ({self._where(j)}) must be single-channel "
                               f"uint16, got {kind}")
        self._check_size(raw, rec.depth, j, what="depth image")
        depth = raw.astype(np.float32) / np.float32(self.depth_scale)
        if self._undistorter is not None:
            depth = self._undistorter.depth(depth)
        return self._cut(depth) if cut else depth

    def _cut(self, depth: np.ndarray) -> np.ndarray:
        """``depth`` without what lies beyond ``max_depth`` (a new array; the same one when there is no cut)."""
        if self.max_depth <= 0:
            return depth
        return np.where(depth > self.max_depth, 0, depth).astype(np.float32)

    def _check_size(self, img: np.ndarray, path: Path, j: int, what: str = "image") -> None:
        w, h = self.intrinsics.width, self.intrinsics.height
        if img.shape[0] != h or img.shape[1] != w:
            raise DynslamError(f"{what} {path} ({self._where(j)}) is {img.shape[1]}x{img.shape[0]}, "
                               f"expected {w}x{h} like the rgb images")

    def _load_labels(self, path: Path, j: int, what: str) -> np.ndarray:
        import cv2

        img = _imread(path, cv2.IMREAD_UNCHANGED, self._where(j))
        if img.ndim != 2:
            raise DynslamError(f"{what} image {path} ({self._where(j)}) must be single-channel")
        self._check_size(img, path, j, what=f"{what} image")
        if self._undistorter is not None:
            img = self._undistorter.nearest(img)
        return img

    def _load(self, j: int) -> Frame:
        rec = self.records[j]
        rgb = self.load_rgb(j)
        full = self.load_depth(j, cut=False)
        depth = self._cut(full)
        inst = dyn = None
        if rec.instances is not None:
            inst = self._load_labels(rec.instances, j, "instance").astype(np.int32)
        if rec.dynamic is not None:
            dyn = self._load_labels(rec.dynamic, j, "dynamic-mask") > 0
        pose = None if rec.pose_c2w is None else rec.pose_c2w.copy()
        return Frame(index=j, timestamp=rec.timestamp, rgb=rgb, depth=depth, pose_c2w=pose,
                     instance_ids=inst, dynamic_mask=dyn, depth_full=None if depth is full else full)


def _imread(path: Path, flags: int, where: str) -> np.ndarray:
    import cv2

    if not Path(path).is_file():
        raise DynslamError(f"image {path} ({where}) is missing")
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, flags) if data.size else None
    if img is None:
        raise DynslamError(f"cannot decode image {path} ({where}): not a readable image file")
    return img
