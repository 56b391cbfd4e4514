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
    segmenter_imgsz: int = opt(640, "yolo-seg: input size when the ONNX model has a dynamic input shape.",
                               min=32, check=(lambda v: v % 32 == 0, "a multiple of 32"))
    prune_ratio: float = opt(0.9, "T_R: drop segment R1 when area(R1 ∩ R2) > T_R · area(R1) for another segment R2.",
                             above=0, max=1)
    min_instance_area: int = opt(64, "Instances with fewer pixels (full resolution) after overlap resolution are dropped to "
            "background.", min=0)
    geometric_width: int = opt(160, "geometric: working width in pixels (ids are upsampled to the frame).", min=8)
    geometric_depth_jump: float = opt(0.04, "geometric: relative depth step |Δd|/d between neighbours that separates segments.",
                                      above=0)
    geometric_normal_angle: float = opt(30.0, "geometric: normal change (degrees) between pixels 3 px apart that separates "
            "segments.", above=0, max=180)
    geometric_color_jump: float = opt(40.0, "geometric: Lab colour difference that separates segments where depth also steps (> "
            "a quarter of the jump).", above=0)
    geometric_min_area: float = opt(0.004, "geometric: smallest segment as a fraction of the image.", min=0, below=1)
    # --- encoding
    encoder: str = opt("effnet-lite0", "Instance encoder: effnet-lite0, onnx, clip, dino, blip, color-hist.",
                       choices=("effnet-lite0", "onnx", "clip", "dino", "blip", "color-hist"))
    encoder_model: str = opt("", "ONNX file of the encoder (for onnx/clip/dino/blip).")
    encoder_input_size: int = opt(0, "Encoder input side in pixels (effnet-lite0 too: its ONNX export is cached per "
                                  "size); 0 = the preset's (224; blip 224 or 364 read from the model).", min=0)
    encoder_mean: list = opt([], "Per-channel mean on the 0-1 scale; empty = the preset's (onnx: ImageNet).")
    encoder_std: list = opt([], "Per-channel std on the 0-1 scale; empty = the preset's (onnx: ImageNet).")
    encoder_output: str = opt("", "Output name or index of the ONNX encoder; empty = the preset's (first output).")
    encoder_pooling: str = opt("auto", "Pooling of the encoder output: auto (B×D as is, tokens → mean, map → mean), mean, cls, "
            "max.", choices=("auto", "mean", "cls", "max"))
    crop_margin: float = opt(0.1, "Margin added around each instance's bounding box, as a fraction of its size.", min=0)
    crop_background: str = opt("grey", "Pixels outside the instance in its crop: grey (the normalisation mean) or zero.",
                               choices=("grey", "zero"))
    encoder_batch: int = opt(32, "Crops per encoder batch.", min=1)
    # --- classifier and continual learning
    hidden: int = opt(128, "Hidden units of the 2-layer MLP classifier g.", min=1)
    lr: float = opt(0.005, "Adam learning rate of classifier updates.", above=0)
    update_steps: int = opt(50, "Maximum Adam steps per classifier update.", min=1)
    min_update_steps: int = opt(5, "Minimum Adam steps per classifier update (then stop once contradictions are fixed).", min=0)
    replay: bool = opt(True, "Replay buffer of instances seen dynamic.")
    replay_samples: int = opt(5, "n_c: instances drawn from the replay buffer per update.", min=0)
    replay_capacity: int = opt(1000, "Replay buffer size (reservoir sampling beyond it).", min=1)
    prior: str = opt("", "Prior classifier file (`dynslam prior fit`); empty = none. OR rule.")
    prior_classes: list = opt([], "Class names that are dynamic by prior (OR rule), for a segmenter with classes: "
                              "yolo-seg on COCO, e.g. [person]. The detector's class head is the prior classifier; "
                              "empty = none.")
    centre_feature: bool = opt(False, "Concatenate the instance's 3-D centre to its embedding.")
    centre_scale: float = opt(1.0, "Multiplier on the 3-D centre (metres) when concatenated.", above=0)
    # --- inconsistency check
    mask_dilation: float = opt(0.008, "The dynamic mask is dilated by this fraction of the image width (0.008: 5 px at "
                               "640) before tracking and mapping: segment borders miss the outline of a mover.", min=0, below=1)
    depth_threshold: float = opt(0.3, "t_d (m): depth difference counted as inconsistent.", above=0)
    pixel_fraction: float = opt(0.05, "t_p: fraction of inconsistent pixels that marks an instance as moving.", above=0, max=1)
    bidirectional: bool = opt(True, "Also segment the rendered view and flag segments seen behind the map (objects that left).")
    backward_current: bool = opt(False, "Backward check: also label current instances moving where they show what a "
                                 "departed object uncovered (off: that is the static background; the departed object's "
                                 "rendered segment is labelled dynamic either way).")
    check_width: int = opt(160, "Width at which the check runs (rendered maps of any size are resized to it).", min=8)
    min_check_pixels: int = opt(12, "Instances with fewer valid pixels at check resolution are not judged.", min=0)
    seed: int = opt(0, "Seed of classifier initialisation and replay sampling.", min=0)
    threads: int = opt(0, "onnxruntime intra-op threads; 0 = its default.", min=0)

    def validate(self, key):
        """Cross-field and list rules (see config.fields)."""
        if self.min_update_steps > self.update_steps:
            yield (f"{key('min_update_steps')} must be <= {key('update_steps')} "
                   f"(got {self.min_update_steps} > {self.update_steps})")
        for name in ("encoder_mean", "encoder_std"):
            value = getattr(self, name)
            vals = numbers(value, 3) if value else []
            if vals is None or (name == "encoder_std" and any(v <= 0 for v in vals)):
                yield (f"{key(name)} must be empty or 3 numbers on the 0-1 scale"
                       f"{' (> 0)' if name == 'encoder_std' else ''} (got {value!r})")
        if not all(isinstance(c, str) and c for c in self.prior_classes):
            yield f"{key('prior_classes')} must be a list of class names (got {self.prior_classes!r})"
