"""Generic ONNX image encoder, with presets for CLIP ViT-B/32, DINOv2 ViT-S/14 and BLIP-2 vision.

The model takes a float32 N×3×S×S image batch ((x/255 − mean)/std); its output (chosen by name or
index) is a B×D embedding, a B×T×D token sequence (pooled: mean, cls or max) or a B×C×h×w map
(pooled over space). Models with a fixed batch of 1 are run crop by crop.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from dynslam_cli.errors import DynslamError
from dynslam_cli.motion.encode_base import (CLIP_MEAN, CLIP_STD, CROP_BACKGROUND, CROP_MARGIN, ENCODER_BATCH, IMAGENET_MEAN,
                                            IMAGENET_STD, crop_fill, l2n, masked_crops, normalise_batch)
from dynslam_cli.motion.onnx_utils import check_image_input, describe_io, ort_session, require_model


@dataclass(frozen=True)
class Preset:
    size: int
    mean: tuple
    std: tuple
    output: str  # name or index ("" = first output)
    pooling: str
    recipe: str


RECIPES = {
    "clip": (
        "pip install open_clip_torch onnx && python -c \"import torch, open_clip; "
        "m, _, _ = open_clip.create_model_and_transforms('ViT-B-32', pretrained='openai'); "
        "v = m.visual.eval(); torch.onnx.export(v, torch.zeros(1, 3, 224, 224), 'clip_vitb32_visual.onnx', "
        "input_names=['images'], output_names=['embedding'], "
        "dynamic_axes={'images': {0: 'b'}, 'embedding': {0: 'b'}}, opset_version=17)\""
    ),
    "dino": (
        "pip install onnx && python -c \"import torch; "
        "m = torch.hub.load('facebookresearch/dinov2', 'dinov2_vits14').eval(); "
        "torch.onnx.export(m, torch.zeros(1, 3, 224, 224), 'dinov2_vits14.onnx', input_names=['images'], "
        "output_names=['embedding'], dynamic_axes={'images': {0: 'b'}, 'embedding': {0: 'b'}}, opset_version=17)\""
    ),
    "blip": (
        "pip install transformers onnx && python -c \"import torch; from transformers import Blip2Model; "
        "v = Blip2Model.from_pretrained('Salesforce/blip2-opt-2.7b').vision_model.eval(); "
        "W = type('W', (torch.nn.Module,), {'forward': lambda s, x: s.v(pixel_values=x).pooler_output}); w = W(); w.v = v; "
        "torch.onnx.export(w, torch.zeros(1, 3, 224, 224), 'blip2_vision.onnx', input_names=['images'], "
        "output_names=['embedding'], dynamic_axes={'images': {0: 'b'}, 'embedding': {0: 'b'}}, opset_version=17)\""
    ),
    "onnx": "point motion.encoder_model at an ONNX image encoder (input N×3×S×S float32)",
}

PRESETS = {
    "onnx": Preset(224, IMAGENET_MEAN, IMAGENET_STD, "", "auto", RECIPES["onnx"]),
    "clip": Preset(224, CLIP_MEAN, CLIP_STD, "", "auto", RECIPES["clip"]),
    "dino": Preset(224, IMAGENET_MEAN, IMAGENET_STD, "", "auto", RECIPES["dino"]),
    "blip": Preset(224, CLIP_MEAN, CLIP_STD, "", "auto", RECIPES["blip"]),
}

EXPECTED_IO = ("an image encoder: one N×3×S×S float input and a B×D embedding, B×T×D tokens or B×C×h×w "
               "feature-map output")

EXPECTED_FILES = {"clip": "clip_vitb32_visual.onnx", "dino": "dinov2_vits14.onnx", "blip": "blip2_vision.onnx"}


def pool(y: np.ndarray, mode: str = "auto") -> np.ndarray:
    """Reduce an encoder output to B×D."""
    y = np.asarray(y, np.float32)
    if y.ndim == 2:
        return y
    if y.ndim == 3:  # B×T×D tokens
        if mode == "cls":
            return y[:, 0]
        if mode == "max":
            return y.max(1)
        return y.mean(1)
    if y.ndim == 4:  # B×C×h×w map
        if mode == "max":
            return y.max((2, 3))
        return y.mean((2, 3))
    raise DynslamError(f"encoder output of shape {y.shape} cannot be pooled to B×D")


class OnnxEncoder:
    backend = "onnxruntime"

    def __init__(self, model_path: str, preset: str = "onnx", input_size: int = 0,
                 mean: Optional[Sequence[float]] = None, std: Optional[Sequence[float]] = None,
                 output: str = "", pooling: str = "auto", margin: float = 0.1, background: str = "grey",
                 batch: int = 32, threads: int = 0, device: str = "cpu"):
        if preset not in PRESETS:
            raise DynslamError(f"unknown ONNX encoder preset '{preset}'; valid: {', '.join(PRESETS)}")
        p = PRESETS[preset]
        self.name = preset
        expected = EXPECTED_FILES.get(preset)
        what = f"{preset} encoder (motion.encoder_model" + (f", e.g. {expected})" if expected else ")")
        path = require_model(model_path, what, f"export it with: {p.recipe}")
        self.session = ort_session(path, threads, device)
        check_image_input(self.session, path, what, EXPECTED_IO)
        inp = self.session.get_inputs()[0]
        self.input_name = inp.name
        shape = inp.shape
        fixed = shape[2] if len(shape) == 4 and isinstance(shape[2], int) else None
        if input_size:
            self.size = int(input_size)
        elif fixed:
            self.size = int(fixed)  # e.g. BLIP-2 exported at 364
        else:
            self.size = p.size
        if fixed and fixed != self.size:
            raise DynslamError(f"{path}: the model takes {fixed}×{fixed} inputs, motion.encoder_input_size is {self.size}")
        self.fixed_batch = shape[0] if isinstance(shape[0], int) else None
        self.mean = tuple(mean) if mean else p.mean
        self.std = tuple(std) if std else p.std
        if len(self.mean) != 3 or len(self.std) != 3:
            raise DynslamError("motion.encoder_mean and encoder_std need 3 values each")
        outs = [o.name for o in self.session.get_outputs()]
        out = output or p.output
        if out == "":
            self.output = outs[0]
        elif str(out).isdigit():
            i = int(out)
            if i >= len(outs):
                raise DynslamError(f"{path} has {len(outs)} outputs ({', '.join(outs)}); output index {i} is out of range")
            self.output = outs[i]
        elif out in outs:
            self.output = out
        else:
            raise DynslamError(f"{path} has no output '{out}'; its outputs: {', '.join(outs)}")
        rank = len(next(o.shape or [] for o in self.session.get_outputs() if o.name == self.output))
        if rank not in (0, 2, 3, 4):  # 0: shape not declared, checked on the dry run below
            raise DynslamError(f"{what}: {path} output '{self.output}' has rank {rank}; it has "
                               f"{describe_io(self.session)}; expected {EXPECTED_IO}")
        self.pooling = pooling or p.pooling
        if self.pooling not in ("auto", "mean", "cls", "max"):
            raise DynslamError(f"motion.encoder_pooling must be auto, mean, cls or max, got '{self.pooling}'")
        self.margin, self.batch = margin, max(1, int(batch))
        self.fill = crop_fill(self.mean, background)
        try:
            self.dim = int(self._run(np.zeros((1, 3, self.size, self.size), np.float32)).shape[1])
        except DynslamError as exc:
            raise DynslamError(f"{what}: {path}: {exc}") from None
        except Exception as exc:  # onnxruntime raises its own exception types
            msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise DynslamError(f"{what}: {path} fails on a {self.size}×{self.size} image batch ({msg}); it has "
                               f"{describe_io(self.session)}; expected {EXPECTED_IO}") from None

    @classmethod
    def from_config(cls, mcfg, threads: int = 0, device: str = "cpu") -> "OnnxEncoder":
        return cls(mcfg.encoder_model, mcfg.encoder, mcfg.encoder_input_size, mcfg.encoder_mean or None,
                   mcfg.encoder_std or None, str(mcfg.encoder_output), mcfg.encoder_pooling, CROP_MARGIN,
                   CROP_BACKGROUND, ENCODER_BATCH, threads, device)

    def _run(self, x: np.ndarray) -> np.ndarray:
        step = self.fixed_batch or self.batch
        outs = []
        for i in range(0, len(x), step):
            xb = x[i:i + step]
            n = len(xb)
            if self.fixed_batch and n < self.fixed_batch:
                xb = np.concatenate([xb, np.zeros((self.fixed_batch - n,) + xb.shape[1:], xb.dtype)])
            y = self.session.run([self.output], {self.input_name: xb})[0]
            outs.append(pool(y, self.pooling)[:n])
        return np.concatenate(outs)

    def encode(self, rgb: np.ndarray, ids_or_masks: np.ndarray) -> np.ndarray:
        crops = masked_crops(rgb, ids_or_masks, self.size, self.margin, self.fill)
        if len(crops) == 0:
            return np.zeros((0, self.dim), np.float32)
        return l2n(self._run(normalise_batch(crops, self.mean, self.std)))
