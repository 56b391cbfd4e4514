"""Configuration of the dynamic-object module (BRIEF.md, 'Learning to forget')."""

from __future__ import annotations

from dataclasses import dataclass

from dynslam_cli.config.fields import numbers, opt


@dataclass
class MotionConfig:
    # --- segmentation
    segmenter: str = opt("geometric", "Instance segmenter: geometric (weightless RGB-D) or yolo-seg (an ONNX file in "
            "`segmenter_model`; fastsam = the same decoder).", choices=("geometric", "yolo-seg", "fastsam"))
    segmenter_model: str = opt("", "ONNX file of a YOLOv8-seg-format model (FastSAM or YOLOv8-seg export).")
    segmenter_conf: float = opt(0.25, "yolo-seg: confidence threshold (FastSAM: 0.4 in its paper).", min=0, max=1)
    segmenter_iou: float = opt(0.7, "yolo-seg: NMS IoU threshold (class-aware for multi-class models).", min=0, max=1)
    geometric_width: int = opt(480, "geometric: working width in pixels (ids are upsampled to the frame); cost grows "
                               "with its square.", min=8)
    # --- encoding
    encoder: str = opt("effnet-lite0", "Instance encoder: effnet-lite0, onnx, clip, dino, blip, color-hist.",
                       choices=("effnet-lite0", "onnx", "clip", "dino", "blip", "color-hist"))
    encoder_model: str = opt("", "ONNX file of the encoder (for onnx/clip/dino/blip).")
    encoder_input_size: int = opt(0, "Encoder input side in pixels (effnet-lite0 too: its ONNX export is cached per "
                                  "size); 0 = the encoder's own: effnet-lite0 160, the onnx presets 224 (blip 224 or "
                                  "364 read from the model).", min=0)
    encoder_mean: list = opt([], "Per-channel mean on the 0-1 scale; empty = the preset's (onnx: ImageNet).")
    encoder_std: list = opt([], "Per-channel std on the 0-1 scale; empty = the preset's (onnx: ImageNet).")
    encoder_output: str = opt("", "Output name or index of the ONNX encoder; empty = the preset's (first output).")
    encoder_pooling: str = opt("auto", "Pooling of the encoder output: auto (B×D as is, tokens → mean, map → mean), mean, cls, "
            "max.", choices=("auto", "mean", "cls", "max"))
    # --- classifier and continual learning
    replay: bool = opt(True, "Replay buffer of instances seen dynamic.")
    replay_samples: int = opt(5, "n_c: instances drawn from the replay buffer per update.", min=0)
    prior: str = opt("", "Prior classifier file (`dynslam prior fit`); empty = none. OR rule.")
    prior_classes: list = opt([], "Class names that are dynamic by prior (OR rule), for a segmenter with classes: "
                              "yolo-seg on COCO, e.g. [person]. The detector's class head is the prior classifier; "
                              "empty = none.")
    centre_feature: bool = opt(False, "Concatenate the instance's 3-D centre to its embedding.")
    # --- inconsistency check
    mask_dilation: float = opt(0.008, "The dynamic mask is dilated by this fraction of the image width (0.008: 5 px at "
                               "640) before tracking and mapping: segment borders miss the outline of a mover.", min=0, below=1)
    depth_threshold: float = opt(0.3, "t_d (m): depth difference counted as inconsistent.", above=0)
    pixel_fraction: float = opt(0.05, "t_p: fraction of inconsistent pixels that marks an instance as moving.", above=0, max=1)
    bidirectional: bool = opt(True, "Also segment the rendered view and flag segments seen behind the map (objects that left).")
    check_width: int = opt(160, "Width at which the check runs (rendered maps of any size are resized to it).", min=8)
    check_every: int = opt(1, "The check (its render, the judging, any classifier update) runs on every N-th frame; "
                           "the classifier labels every frame. 2 makes dynamic mode about a fifth faster on a CPU, "
                           "with slightly coarser masks and forgetting (docs/experiments.md).", min=1)

    def validate(self, key):
        """Cross-field and list rules (see config.fields)."""
        for name in ("encoder_mean", "encoder_std"):
            value = getattr(self, name)
            vals = numbers(value, 3) if value else []
            if vals is None or (name == "encoder_std" and any(v <= 0 for v in vals)):
                yield (f"{key(name)} must be empty or 3 numbers on the 0-1 scale"
                       f"{' (> 0)' if name == 'encoder_std' else ''} (got {value!r})")
        if not all(isinstance(c, str) and c for c in self.prior_classes):
            yield f"{key('prior_classes')} must be a list of class names (got {self.prior_classes!r})"
