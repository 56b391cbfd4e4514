"""`dynslam prior fit`: pre-train the prior classifier (people vs the rest) from labelled crops.

Sources of labelled instances:

* a folder of images + a YOLOv8-seg ONNX model: instances of the positive classes (person) are
  positives; other detected classes and the background left between detections (cut into a 3×3
  grid of connected pieces) are negatives;
* synthetic scene folders (``dynslam synth``; or presets rendered here): the ground-truth
  instances (instances/) and the configured segmenter's segments of each frame, labelled by the
  dynamic/ masks (dynamic when more than half of the pixels move); the room (id 0) is a negative.

The crops are encoded with the configured encoder; a 2-layer MLP (the classifier g's shape) is
trained with class-balanced BCE on a random split and its held-out accuracy is reported.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import cv2
import numpy as np

from dynslam_cli.errors import DynslamError

IMAGE_EXT = (".jpg", ".jpeg", ".png", ".bmp", ".webp")


@dataclass
class PriorFitResult:
    out: Path
    encoder: str
    samples: int
    positives: int
    train_accuracy: float
    test_accuracy: float
    test_samples: int
    test_precision: float
    test_recall: float
    sources: dict = field(default_factory=dict)
    seconds: float = 0.0


def _read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise DynslamError(f"cannot read image {path}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def background_pieces(taken: np.ndarray, grid: int = 3, min_frac: float = 0.02) -> list[np.ndarray]:
    """Connected pieces of the pixels in no detection, cut by a grid×grid raster (negatives)."""
    h, w = taken.shape
    out = []
    for gy in range(grid):
        for gx in range(grid):
            cell = np.zeros_like(taken)
            cell[gy * h // grid:(gy + 1) * h // grid, gx * w // grid:(gx + 1) * w // grid] = True
            free = (cell & ~taken).astype(np.uint8)
            n, lab = cv2.connectedComponents(free, connectivity=4)
            for k in range(1, n):
                m = lab == k
                if m.mean() >= min_frac:
                    out.append(m)
    return out


def samples_from_images(folder: Path, yolo_model: str, encoder, mcfg, positive: Sequence[str] = ("person",),
                        limit: int = 0, threads: int = 0) -> tuple[np.ndarray, np.ndarray]:
    from dynslam_cli.motion.segment_yolo import YoloSegSegmenter

    folder = Path(folder)
    if not folder.is_dir():
        raise DynslamError(f"image folder not found: {folder}")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXT)
    if limit:
        files = files[:limit]
    if not files:
        raise DynslamError(f"no images ({', '.join(IMAGE_EXT)}) in {folder}")
    seg = YoloSegSegmenter(yolo_model, conf=mcfg.segmenter_conf, iou=mcfg.segmenter_iou, threads=threads)
    if not seg.names:
        raise DynslamError(f"{yolo_model} carries no class names (a FastSAM export?); prior fit needs a "
                           "YOLOv8-seg model trained on classes such as COCO's person")
    pos_ids = {k for k, v in seg.names.items() if v in set(positive)}
    if not pos_ids:
        raise DynslamError(f"{yolo_model} has no class named {', '.join(positive)}")
    feats, labels = [], []
    for f in files:
        rgb = _read_rgb(f)
        s = seg.segment(rgb)
        masks = [s.ids == k + 1 for k in range(s.count)]
        lab = [1.0 if int(c) in pos_ids else 0.0 for c in s.class_ids]
        bg = background_pieces(s.ids > 0)
        masks += bg
        lab += [0.0] * len(bg)
        if masks:
            feats.append(encoder.encode(rgb, np.stack(masks)))
            labels.append(np.array(lab, np.float32))
    if not feats:
        raise DynslamError(f"no instances found in the images of {folder}")
    return np.concatenate(feats), np.concatenate(labels)


def _synth_frames(folder: Path, frames: int, stride: int):
    inst_dir, dyn_dir, rgb_dir, depth_dir = (folder / n for n in ("instances", "dynamic", "rgb", "depth"))
    if not inst_dir.is_dir() or not dyn_dir.is_dir():
        raise DynslamError(f"{folder} is not a synthetic scene folder (needs instances/ and dynamic/)")
    names = sorted(p.name for p in inst_dir.glob("*.png"))[::max(1, stride)]
    if frames:
        names = names[:frames]
    scale = 5000.0
    meta = folder / "synth.json"
    if meta.is_file():
        import json

        scale = float(json.loads(meta.read_text()).get("depth_scale", scale))
    for n in names:
        rgb = _read_rgb(rgb_dir / n)
        inst = cv2.imread(str(inst_dir / n), cv2.IMREAD_UNCHANGED).astype(np.int32)
        dyn = cv2.imread(str(dyn_dir / n), cv2.IMREAD_UNCHANGED) > 127
        d = cv2.imread(str(depth_dir / n), cv2.IMREAD_UNCHANGED) if (depth_dir / n).is_file() else None
        depth = d.astype(np.float32) / scale if d is not None else None
        yield rgb, depth, inst, dyn


def samples_from_synth(folder: Path, encoder, segmenter=None, frames: int = 30, stride: int = 1,
                       min_pixels: int = 100) -> tuple[np.ndarray, np.ndarray]:
    feats, labels = [], []
    for rgb, depth, inst, dyn in _synth_frames(Path(folder), frames, stride):
        masks, lab = [], []
        for k in np.unique(inst):
            m = inst == k
            if m.sum() < min_pixels:
                continue
            masks.append(m)
            lab.append(1.0 if dyn[m].mean() > 0.5 else 0.0)
        if segmenter is not None and depth is not None:
            s = segmenter.segment(rgb, depth)
            for k in range(1, s.count + 1):
                m = s.ids == k
                if m.sum() >= min_pixels:
                    masks.append(m)
                    lab.append(1.0 if dyn[m].mean() > 0.5 else 0.0)
        if masks:
            feats.append(encoder.encode(rgb, np.stack(masks)))
            labels.append(np.array(lab, np.float32))
    if not feats:
        raise DynslamError(f"no labelled instances in {folder}")
    return np.concatenate(feats), np.concatenate(labels)


def resolve_synth(spec: str, cfg, frames: int) -> Path:
    """A synthetic scene folder: ``spec`` itself when it is one, else preset ``spec`` rendered into
    the cache folder (once)."""
    p = Path(spec)
    if p.is_dir():
        return p
    from dynslam_cli.motion.onnx_utils import cache_dir

    try:
        from dynslam_cli.synth.render import PRESETS, render_preset
    except ImportError as exc:
        raise DynslamError(f"synthetic renderer unavailable ({exc}); pass a scene folder to --synth") from None
    if spec not in PRESETS:
        raise DynslamError(f"--synth {spec}: neither a folder nor a preset ({', '.join(PRESETS)})")
    s = cfg.synth
    out = cache_dir() / "prior-synth" / f"{spec}-{s.width}x{s.height}-s{s.seed}-{frames}"
    if not (out / "synth.json").is_file():
        render_preset(spec, out, s, frames, progress=False)
    return out


def fit_classifier(x: np.ndarray, y: np.ndarray, hidden: int, steps: int = 300, lr: float = 0.01, seed: int = 0):
    from dynslam_cli.motion.classifier import MotionClassifier

    clf = MotionClassifier(x.shape[1], hidden, lr=lr, seed=seed)
    pos = max(float(y.sum()), 1.0)
    neg = max(float(len(y) - y.sum()), 1.0)
    w = np.where(y > 0.5, len(y) / (2 * pos), len(y) / (2 * neg)).astype(np.float32)
    clf.fit_steps(x, y, max_steps=steps, min_steps=steps, weights=w)
    return clf


def fit_prior(out: str | Path, cfg, images: Optional[Path] = None, yolo: Optional[str] = None,
              synth: Sequence[str] = (), frames: int = 30, stride: int = 1, test_fraction: float = 0.25,
              steps: int = 300, positive: Sequence[str] = ("person",), seed: int = 0) -> PriorFitResult:
    """Collect labelled crops, train the prior, save it to ``out`` (atomically), report accuracy."""
    from dynslam_cli.motion.classifier import save_prior
    from dynslam_cli.motion.encoders import make_encoder
    from dynslam_cli.motion.module import HIDDEN

    t0 = time.perf_counter()
    if images is None and not synth:
        raise DynslamError("prior fit needs --images DIR (with --yolo) and/or --synth PRESET|DIR")
    mcfg = cfg.motion
    threads = int(cfg.run.threads)
    encoder = make_encoder(mcfg, threads)
    xs, ys, sources = [], [], {}
    if images is not None:
        model = yolo or mcfg.segmenter_model
        x, y = samples_from_images(Path(images), model, encoder, mcfg, positive, threads=threads)
        xs.append(x)
        ys.append(y)
        sources[str(images)] = {"samples": int(len(y)), "positives": int(y.sum())}
    if synth:
        from dynslam_cli.motion.segmenters import make_segmenter

        segmenter = make_segmenter(mcfg) if mcfg.segmenter == "geometric" else None
        for spec in synth:
            folder = resolve_synth(spec, cfg, frames)
            x, y = samples_from_synth(folder, encoder, segmenter, frames, stride)
            xs.append(x)
            ys.append(y)
            sources[str(spec)] = {"samples": int(len(y)), "positives": int(y.sum())}
    x = np.concatenate(xs).astype(np.float32)
    y = np.concatenate(ys).astype(np.float32)
    if y.sum() < 2 or (len(y) - y.sum()) < 2:
        raise DynslamError(f"prior fit needs at least 2 positives and 2 negatives, got {int(y.sum())} of {len(y)}")
    rng = np.random.default_rng(seed)
    test = np.zeros(len(y), bool)
    for cls in (0.0, 1.0):  # stratified split
        idx = np.nonzero(y == cls)[0]
        rng.shuffle(idx)
        test[idx[: max(1, int(round(test_fraction * len(idx))))]] = True
    clf = fit_classifier(x[~test], y[~test], HIDDEN, steps, seed=seed)
    pred = clf.predict(x)
    yb = y > 0.5
    acc_train = float((pred[~test] == yb[~test]).mean())
    acc_test = float((pred[test] == yb[test]).mean())
    tp = float((pred[test] & yb[test]).sum())
    prec = tp / max(float(pred[test].sum()), 1.0)
    rec = tp / max(float(yb[test].sum()), 1.0)
    # the saved prior is refitted on everything
    final = fit_classifier(x, y, HIDDEN, steps, seed=seed)
    meta = {"positive": list(positive), "samples": int(len(y)), "positives": int(y.sum()),
            "test_accuracy": acc_test, "train_accuracy": acc_train, "sources": sources}
    save_prior(out, final, encoder.name, meta)
    return PriorFitResult(Path(out), encoder.name, int(len(y)), int(y.sum()), acc_train, acc_test, int(test.sum()),
                          prec, rec, sources, time.perf_counter() - t0)
