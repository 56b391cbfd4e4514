"""The encoder factory: the encoder ``motion.encoder`` names."""

from __future__ import annotations

from dynslam_cli.errors import DynslamError
from dynslam_cli.motion.encode_base import Encoder


def make_encoder(mcfg, threads: int = 0, device: str = "cpu") -> Encoder:
    """The encoder named by ``motion.encoder``; ``threads``: its runtime's threads (OpenVINO or onnxruntime; run.threads; 0 = its
    default); ``device``: the run's device type (``cuda``: EfficientNet in torch on the GPU, ONNX models on
    onnxruntime's CUDA provider where it is installed)."""
    name = mcfg.encoder
    if name == "effnet-lite0":
        from dynslam_cli.motion.encode_effnet import EffNetLite0Encoder

        return EffNetLite0Encoder.from_config(mcfg, threads, device)
    if name in ("onnx", "clip", "dino", "blip"):
        from dynslam_cli.motion.encode_onnx import OnnxEncoder

        return OnnxEncoder.from_config(mcfg, threads, device)
    if name == "color-hist":
        from dynslam_cli.motion.encode_hist import ColorHistEncoder

        return ColorHistEncoder()
    raise DynslamError(f"unknown motion.encoder '{name}'; valid: effnet-lite0, onnx, clip, dino, blip, color-hist")
