"""The segmenter factory: the segmenter ``motion.segmenter`` names."""

from __future__ import annotations

from dynslam_cli.errors import DynslamError
from dynslam_cli.motion.segment_base import Segmenter


def make_segmenter(mcfg, intrinsics=None, threads: int = 0, device: str = "cpu") -> Segmenter:
    """The segmenter named by ``motion.segmenter`` (geometric | yolo-seg | fastsam); ``threads``: onnxruntime
    intra-op threads (run.threads; 0 = its default)."""
    name = mcfg.segmenter
    if name == "geometric":
        from dynslam_cli.motion.segment_geometric import GeometricSegmenter

        return GeometricSegmenter.from_config(mcfg, intrinsics)
    if name in ("yolo-seg", "fastsam"):
        from dynslam_cli.motion.segment_yolo import YoloSegSegmenter

        return YoloSegSegmenter.from_config(mcfg, threads, device)
    raise DynslamError(f"unknown motion.segmenter '{name}'; valid: geometric, yolo-seg, fastsam")
