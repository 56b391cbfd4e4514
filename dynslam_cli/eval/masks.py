"""Motion-mask quality against the synthetic scenes' ground-truth dynamic masks.

Reads the run's ``masks/<ts>.png`` (uint8, 255 = dynamic; any value > 127 counts as dynamic)
and the scene's ``dynamic/<ts>.png`` (same convention), matched by timestamp (file stem, or
the same float value within 1e-4 s).  Per frame, with P the predicted and G the true dynamic
pixels: IoU = |P∩G| / |P∪G|, precision = |P∩G| / |P|, recall = |P∩G| / |G| (undefined, null,
when the denominator is empty; IoU of a frame with neither is 1).

Summaries: ``moving`` = means over frames where a mover is visible (G non-empty; precision over
those of them with a non-empty prediction); ``all`` = means over every matched frame (IoU 1 on
empty/empty frames), plus ``pooled_iou`` = IoU over all pixels of all frames.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from dynslam_cli.errors import DynslamError
from dynslam_cli.eval import runs
from dynslam_cli.utils.io import write_json_atomic


@dataclass
class MaskResult:
    frames: int
    frames_moving: int
    mean_iou_moving: Optional[float]
    mean_precision_moving: Optional[float]
    mean_recall_moving: Optional[float]
    mean_iou_all: Optional[float]
    mean_precision_all: Optional[float]
    mean_recall_all: Optional[float]
    pooled_iou: Optional[float]
    unmatched_masks: int
    per_frame: list = field(default_factory=list)

    def to_json(self) -> dict:
        return asdict(self)


def read_mask(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DynslamError(f"cannot read mask image {path}")
    if img.ndim == 3:
        img = img[..., 0]
    return img > 127


def frame_scores(pred: np.ndarray, gt: np.ndarray) -> dict:
    tp = int(np.logical_and(pred, gt).sum())
    npred, ngt = int(pred.sum()), int(gt.sum())
    union = npred + ngt - tp
    return {
        "iou": (tp / union) if union else 1.0,
        "precision": (tp / npred) if npred else None,
        "recall": (tp / ngt) if ngt else None,
        "tp": tp, "pred": npred, "gt": ngt,
    }


def _mean(vals) -> Optional[float]:
    vals = [v for v in vals if v is not None]
    return float(np.mean(vals)) if vals else None


def _index_by_time(folder: Path) -> dict[str, Path]:
    return {p.stem: p for p in sorted(folder.glob("*.png"))}


def _match(stem: str, gt_index: dict[str, Path], gt_times: np.ndarray, gt_keys: list[str]) -> Optional[Path]:
    if stem in gt_index:
        return gt_index[stem]
    try:
        t = float(stem)
    except ValueError:
        return None
    if len(gt_times) == 0:
        return None
    i = int(np.argmin(np.abs(gt_times - t)))
    return gt_index[gt_keys[i]] if abs(gt_times[i] - t) < 1e-4 else None


def compute_mask_metrics(mask_dir: str | Path, gt_dir: str | Path) -> MaskResult:
    mask_dir, gt_dir = Path(mask_dir), Path(gt_dir)
    if not mask_dir.is_dir():
        raise DynslamError(f"mask folder not found: {mask_dir} (run with run.save_masks=true)")
    if not gt_dir.is_dir():
        raise DynslamError(f"ground-truth dynamic-mask folder not found: {gt_dir}")
    preds = _index_by_time(mask_dir)
    if not preds:
        raise DynslamError(f"no masks (*.png) in {mask_dir}")
    gt_index = _index_by_time(gt_dir)
    gt_keys, gt_t = [], []
    for k in gt_index:
        try:
            gt_t.append(float(k))
            gt_keys.append(k)
        except ValueError:
            pass
    gt_times = np.asarray(gt_t)
    per_frame, unmatched = [], 0
    tp_sum = union_sum = 0
    for stem, ppath in preds.items():
        gpath = _match(stem, gt_index, gt_times, gt_keys)
        if gpath is None:
            unmatched += 1
            continue
        pred, gt = read_mask(ppath), read_mask(gpath)
        if pred.shape != gt.shape:
            raise DynslamError(f"mask {ppath} is {pred.shape[1]}x{pred.shape[0]} but ground truth {gpath} is "
                               f"{gt.shape[1]}x{gt.shape[0]}")
        s = frame_scores(pred, gt)
        tp_sum += s["tp"]
        union_sum += s["pred"] + s["gt"] - s["tp"]
        per_frame.append({"timestamp": stem, **s})
    if not per_frame:
        raise DynslamError(f"none of the {len(preds)} masks in {mask_dir} has a ground-truth mask in {gt_dir}")
    moving = [f for f in per_frame if f["gt"] > 0]
    return MaskResult(
        frames=len(per_frame), frames_moving=len(moving),
        mean_iou_moving=_mean(f["iou"] for f in moving),
        mean_precision_moving=_mean(f["precision"] for f in moving),
        mean_recall_moving=_mean(f["recall"] for f in moving),
        mean_iou_all=_mean(f["iou"] for f in per_frame),
        mean_precision_all=_mean(f["precision"] for f in per_frame),
        mean_recall_all=_mean(f["recall"] for f in per_frame),
        pooled_iou=(tp_sum / union_sum) if union_sum else None,
        unmatched_masks=unmatched, per_frame=per_frame,
    )


def has_masks(run_dir: Path) -> bool:
    d = Path(run_dir) / "masks"
    return d.is_dir() and any(d.glob("*.png"))


def evaluate_run_masks(run_dir: str | Path, gt_dir: Optional[str | Path] = None,
                       include_incomplete: bool = False) -> MaskResult:
    """Mask metrics of a synthetic run folder; writes mask_metrics.json.

    A run whose run.json is not completed is an error unless ``include_incomplete``.
    """
    run_dir = runs.require_completed(run_dir, include_incomplete)
    if gt_dir is None:
        sp = runs.sequence_path(run_dir)
        if sp is None or not (sp / "dynamic").is_dir():
            raise DynslamError(f"run {run_dir} is not a synthetic run with ground-truth masks "
                               "(run.json sequence.path has no dynamic/ folder); pass --gt-dir")
        gt_dir = sp / "dynamic"
    res = compute_mask_metrics(run_dir / "masks", gt_dir)
    write_json_atomic(run_dir / "mask_metrics.json", res.to_json())
    return res
