"""Weightless RGB-D instance segmenter: depth discontinuities + surface normals + colour.

Works at a reduced resolution (``motion.geometric_width``, 480 px by default):

1. depth is median-filtered, back-projected and normals are taken from 2-px central differences;
2. a pixel is an *edge* when, towards a 4-neighbour, the depth steps by more than
   ``depth_jump``·d, the normal turns by more than ``normal_angle``, or the Lab colour changes by more
   than ``color_jump`` while the depth also steps by a quarter of the jump; invalid depth is an edge;
3. edges are dilated by one pixel (so that thin bridges do not leak regions into each other), the
   remaining pixels are split into 4-connected components, components under ``min_area`` are
   discarded, and edge pixels, dropped specks and pixels without depth (holes) within 6 px of a
   component join the nearest one;
4. the id map is upsampled to the frame (nearest).

Besides the ids (what the instances are encoded, judged and tracked on), a segmentation carries each
segment's **extent** (``Segmentation.extent``): edge pixels and dropped specks join the component their
depth continues instead of the nearest one (grown breadth first across 4-neighbour steps under
``depth_jump``, however far: a band pixel beside a depth step joins the side at its depth, the specks a
mover's creases and colours cut off join the mover), then holes within 6 px the nearest component.  A
dynamic instance masks the part of its extent that stands where recent keyframes saw empty space
(:func:`dynslam_cli.motion.checkable.bounded_extent`).

The point image, the normals and the edge tests of steps 1–2 are numba kernels
(:mod:`dynslam_cli.motion._segment_kernels`: the same bits as numpy's whole-array expressions), and so
is the extent's growth; the filters, dilations, components and hole fill are OpenCV's.

Planar structures (walls, floor, table tops) become segments of their own, separated at creases;
objects standing in front of them are separated by the depth step (and their contact line by the
normal crease).
"""

from __future__ import annotations

from typing import Optional

import cv2
import numpy as np

from dynslam_cli.motion import _segment_kernels as kernels
from dynslam_cli.motion.segment_base import MIN_INSTANCE_AREA, relabel
from dynslam_cli.motion.types import Segmentation, intrinsics_tuple

# Edges: a relative depth step |dd|/d between neighbours, a normal change (degrees) between pixels 3 px apart, or a
# Lab colour difference where the depth also steps (> a quarter of the jump).
DEPTH_JUMP = 0.04
NORMAL_ANGLE = 30.0
COLOR_JUMP = 40.0
# Smallest segment as a fraction of the image: 0.2 % (synthetic movers are small and far; the oracle mask IoU, each
# segment labelled by its ground-truth majority, is 0.85 / 0.77 on walker / kidnap at 480 px, 640x480 frames:
# benchmarks/bench_segment.py, docs/experiments.md).
MIN_AREA = 0.002
_NO_LAB = np.zeros((0, 0, 3), np.float32)


def _intrinsics_tuple(intrinsics, w: int, h: int) -> tuple[float, float, float, float]:
    if intrinsics is None:
        f = 525.0 * w / 640.0
        return f, f, (w - 1) / 2.0, (h - 1) / 2.0
    return intrinsics_tuple(intrinsics)


class GeometricSegmenter:
    name = "geometric"

    def __init__(self, intrinsics=None, width: int = 480, depth_jump: float = DEPTH_JUMP,
                 normal_angle: float = NORMAL_ANGLE, color_jump: float = COLOR_JUMP, min_area: float = MIN_AREA,
                 min_instance_area: int = MIN_INSTANCE_AREA,
                 fill_radius: int = 6):
        self.intrinsics = intrinsics
        self.width = int(width)
        self.depth_jump = float(depth_jump)
        self.cos_normal = float(np.cos(np.deg2rad(normal_angle)))
        self.color_jump = float(color_jump)
        self.min_area = float(min_area)
        self.min_instance_area = int(min_instance_area)
        self.fill_radius = int(fill_radius)
        self.normal_offset = 3

    @classmethod
    def from_config(cls, mcfg, intrinsics=None) -> "GeometricSegmenter":
        return cls(intrinsics, mcfg.geometric_width)

    def segment(self, rgb: Optional[np.ndarray], depth: np.ndarray) -> Segmentation:
        H, W = depth.shape[:2]

        def up(a):
            return cv2.resize(a.astype(np.float32), (W, H), interpolation=cv2.INTER_NEAREST).astype(np.int32) \
                if a.shape != (H, W) else a

        ids_small, extent_small = self.segment_small(rgb, depth, extent=True)
        ids, old = relabel(up(ids_small), self.min_instance_area)
        lut = np.zeros(max(int(extent_small.max()), int(old.max(initial=0))) + 1, np.int32)
        lut[old] = np.arange(1, len(old) + 1, dtype=np.int32)
        k = int(ids.max())
        return Segmentation(ids, -np.ones(k, np.int64), np.ones(k, np.float32), extent=lut[up(extent_small)])

    def segment_small(self, rgb: Optional[np.ndarray], depth: np.ndarray, extent: bool = False):
        """Id map at the working resolution; with ``extent``, also the segments' extent (step 3's growth)."""
        H, W = depth.shape[:2]
        s = min(1.0, self.width / W)
        w, h = max(8, int(round(W * s))), max(8, int(round(H * s)))
        d = cv2.resize(depth.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST) if (w, h) != (W, H) \
            else depth.astype(np.float32)
        d = np.nan_to_num(d, nan=0.0, posinf=0.0, neginf=0.0)
        d = np.where(d > 0, d, 0).astype(np.float32)
        dm = cv2.medianBlur(d, 5)
        dm = np.where((d > 0) & (dm > 0), dm, 0).astype(np.float32)
        valid = dm > 0
        fx, fy, cx, cy = _intrinsics_tuple(self.intrinsics, W, H)
        fx, fy, cx, cy = fx * w / W, fy * h / H, (cx + 0.5) * w / W - 0.5, (cy + 0.5) * h / H - 0.5
        u = (np.arange(w, dtype=np.float32) - cx) / fx
        v = (np.arange(h, dtype=np.float32) - cy) / fy
        # normals from central differences over 2 px of the validity-weighted 5×5 box-filtered points
        # (the points are 0 where there is no depth)
        wv = cv2.blur(valid.astype(np.float32), (5, 5))
        n = kernels.normals(cv2.blur(kernels.points(dm, u, v), (5, 5)), wv)
        nvalid = valid.copy()
        nvalid[:, 1:-1] &= valid[:, 2:] & valid[:, :-2]
        nvalid[1:-1] &= valid[2:] & valid[:-2]
        nvalid[[0, -1], :] = False
        nvalid[:, [0, -1]] = False
        lab = None
        if rgb is not None and self.color_jump > 0:
            small = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA) if (w, h) != (W, H) else rgb
            lab = cv2.cvtColor(np.ascontiguousarray(small), cv2.COLOR_RGB2LAB).astype(np.float32)
            lab[..., 0] *= 100.0 / 255.0
        edge = kernels.step_edges(dm, _NO_LAB if lab is None else lab, self.depth_jump, self.color_jump,
                                  0.25 * self.depth_jump)
        # normal creases: compare normals o px apart (the box filter spreads a crease over a few px);
        # the box filter mixes surfaces across depth steps, so normals near those are not compared
        smooth = nvalid & ~cv2.dilate(edge.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        kernels.crease_edges(n, smooth, self.normal_offset, self.cos_normal, edge)
        core = ~cv2.dilate(edge.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        n_lab, lab_map = cv2.connectedComponents(core.astype(np.uint8), connectivity=4)
        counts = np.bincount(lab_map.ravel(), minlength=n_lab)
        min_px = max(4, int(self.min_area * w * h))
        keep = counts >= min_px
        keep[0] = False
        lut = np.where(keep, np.arange(n_lab), 0).astype(np.int32)
        lab_map = lut[lab_map]
        # ids: edge pixels, dropped specks and pixels without depth (sensor holes, which the median
        # filter widens) join the nearest kept component within fill_radius
        ids = self._fill_nearest(lab_map, np.ones_like(valid)) if keep.any() else lab_map
        if not extent:
            return ids
        # extent: edge pixels and dropped specks join the component their depth continues, then holes the
        # nearest component within fill_radius
        grown = kernels.grow_continuous(lab_map, dm, self.depth_jump)
        return ids, (self._fill_nearest(grown, ~valid) if keep.any() else grown)

    def _fill_nearest(self, lab_map: np.ndarray, may: np.ndarray) -> np.ndarray:
        """``lab_map`` with its unlabelled pixels where ``may`` given to the nearest labelled pixel's
        label within ``fill_radius``."""
        out = lab_map.astype(np.int32).copy()
        unl = out == 0
        if unl.any():
            dist, nearest = cv2.distanceTransformWithLabels(unl.astype(np.uint8), cv2.DIST_L2, 3,
                                                            labelType=cv2.DIST_LABEL_PIXEL)
            # DIST_LABEL_PIXEL numbers the labelled (zero) pixels in row-major scan order starting at 1
            pix_lab = np.concatenate([np.zeros(1, np.int32), out[~unl]])
            fill = unl & may & (dist <= self.fill_radius)
            out[fill] = pix_lab[nearest[fill]]
        return out
