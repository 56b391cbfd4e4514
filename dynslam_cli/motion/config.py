"""Configuration of the dynamic-object module (BRIEF.md, 'Learning to forget')."""

from __future__ import annotations

from dataclasses import dataclass

from dynslam_cli.config.fields import opt


@dataclass
class MotionConfig:
    segmenter: str = opt("geometric", "Instance segmenter: geometric (weightless RGB-D) or yolo-seg (an ONNX file in `segmenter_model`).")
    segmenter_model: str = opt("", "ONNX file of a YOLOv8-seg-format model (FastSAM or YOLOv8-seg export).")
    encoder: str = opt("effnet-lite0", "Instance encoder: effnet-lite0, onnx, clip, dino, blip, color-hist.")
    encoder_model: str = opt("", "ONNX file of the encoder (for onnx/clip/dino/blip).")
    depth_threshold: float = opt(0.3, "t_d (m): depth difference counted as inconsistent.")
    pixel_fraction: float = opt(0.05, "t_p: fraction of inconsistent pixels that marks an instance as moving.")
    replay: bool = opt(True, "Replay buffer of instances seen dynamic.")
    replay_samples: int = opt(5, "n_c: instances drawn from the replay buffer per update.")
    prior: str = opt("", "Prior classifier file (`dynslam prior fit`); empty = none. OR rule.")
    centre_feature: bool = opt(False, "Concatenate the instance's 3-D centre to its embedding.")
