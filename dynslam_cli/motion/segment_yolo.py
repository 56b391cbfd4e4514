"""YOLOv8-seg-format ONNX instance segmenter (YOLOv8-seg, FastSAM).

Outputs: ``output0`` 1×(4+nc+nm)×A (box cx,cy,w,h in input pixels, nc class scores, nm mask
coefficients), ``output1`` 1×nm×mh×mw mask prototypes. FastSAM has nc = 1.
"""

from __future__ import annotations

import ast
from typing import Optional

import cv2
import numpy as np

from dynslam_cli.errors import DynslamError
from dynslam_cli.motion.onnx_utils import check_image_input, describe_io, fixed, ort_session, require_model
from dynslam_cli.motion.segment_base import MIN_INSTANCE_AREA, PRUNE_RATIO, masks_to_ids, prune_parts
from dynslam_cli.motion.types import Segmentation

# Input size when the ONNX model has a dynamic input shape.
IMGSZ = 640

EXPECTED_IO = ("YOLOv8-seg / FastSAM outputs: output0 1×(4+C+32)×N (boxes, C class scores, 32 mask "
               "coefficients) and output1 1×32×H×W mask prototypes, from one 1×3×H×W float input")

FASTSAM_RECIPE = ("export it with `pip install ultralytics` then "
                  "`python -c \"from ultralytics import FastSAM; FastSAM('FastSAM-s.pt').export(format='onnx', imgsz=640)\"` "
                  "(YOLOv8-seg: `YOLO('yolov8n-seg.pt').export(format='onnx')`) and set motion.segmenter_model=FILE")


def letterbox(img: np.ndarray, new_shape: tuple[int, int], color: int = 114
              ) -> tuple[np.ndarray, float, tuple[int, int]]:
    """Resize keeping the aspect ratio and pad to ``new_shape`` (h, w) with grey.
    Returns (image, scale r, (left, top) padding); original = (letterboxed − pad) / r."""
    h, w = img.shape[:2]
    nh, nw = new_shape
    r = min(nh / h, nw / w)
    uw, uh = int(round(w * r)), int(round(h * r))
    dw, dh = (nw - uw) / 2.0, (nh - uh) / 2.0
    if (uw, uh) != (w, h):
        img = cv2.resize(img, (uw, uh), interpolation=cv2.INTER_LINEAR)
    top, bottom = int(round(dh - 0.1)), int(round(dh + 0.1))
    left, right = int(round(dw - 0.1)), int(round(dw + 0.1))
    out = cv2.copyMakeBorder(img, top, bottom, left, right, cv2.BORDER_CONSTANT, value=(color,) * 3)
    return out, r, (left, top)


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU between (N,4) and (M,4) xyxy boxes."""
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    wh = np.clip(rb - lt, 0, None)
    inter = wh[..., 0] * wh[..., 1]
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    return inter / np.maximum(area_a[:, None] + area_b[None] - inter, 1e-9)


def nms(boxes: np.ndarray, scores: np.ndarray, iou_thres: float, classes: Optional[np.ndarray] = None,
        max_det: int = 300) -> np.ndarray:
    """Greedy non-maximum suppression; class-aware when ``classes`` is given. Returns kept indices
    in decreasing score order."""
    if len(boxes) == 0:
        return np.zeros(0, np.int64)
    b = boxes.astype(np.float64)
    if classes is not None:  # offset boxes per class so different classes never overlap
        b = b + (classes.astype(np.float64) * (b.max() + 1.0))[:, None]
    order = np.argsort(-scores, kind="stable")
    keep: list[int] = []
    while order.size and len(keep) < max_det:
        i = int(order[0])
        keep.append(i)
        if order.size == 1:
            break
        ious = box_iou(b[i:i + 1], b[order[1:]])[0]
        order = order[1:][ious <= iou_thres]
    return np.array(keep, np.int64)


def xywh2xyxy(x: np.ndarray) -> np.ndarray:
    y = np.empty_like(x)
    y[:, 0] = x[:, 0] - x[:, 2] / 2
    y[:, 1] = x[:, 1] - x[:, 3] / 2
    y[:, 2] = x[:, 0] + x[:, 2] / 2
    y[:, 3] = x[:, 1] + x[:, 3] / 2
    return y


def decode(out0: np.ndarray, protos: np.ndarray, orig_hw: tuple[int, int], input_hw: tuple[int, int],
           r: float, pad: tuple[int, int], conf: float = 0.25, iou: float = 0.7, class_aware: bool = True,
           max_det: int = 100, mask_thres: float = 0.5):
    """Decode raw YOLOv8-seg outputs into boxes (original pixels, xyxy), scores, classes and
    full-resolution bool masks (N, H, W)."""
    nm = protos.shape[1]
    pred = out0[0].T  # (A, 4+nc+nm)
    nc = pred.shape[1] - 4 - nm
    if nc < 1:
        raise ValueError(f"output0 has {pred.shape[1]} channels, too few for 4 + classes + {nm} coefficients")
    cls_scores = pred[:, 4:4 + nc]
    cls = cls_scores.argmax(1)
    score = cls_scores[np.arange(len(pred)), cls]
    sel = score > conf
    pred, cls, score = pred[sel], cls[sel], score[sel]
    H, W = orig_hw
    if len(pred) == 0:
        return np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64), np.zeros((0, H, W), bool)
    boxes_in = xywh2xyxy(pred[:, :4])
    keep = nms(boxes_in, score, iou, cls if (class_aware and nc > 1) else None, max_det)
    pred, cls, score, boxes_in = pred[keep], cls[keep], score[keep], boxes_in[keep]
    coeffs = pred[:, 4 + nc:]
    _, _, mh, mw = protos.shape
    m = coeffs @ protos[0].reshape(nm, -1)
    m = 1.0 / (1.0 + np.exp(-m))
    m = m.reshape(-1, mh, mw)
    ih, iw = input_hw
    # the un-padded part of the prototype grid
    sx, sy = mw / iw, mh / ih
    left, top = pad
    x0, y0 = int(round(left * sx)), int(round(top * sy))
    x1 = int(round((iw - left) * sx)) if left else mw
    y1 = int(round((ih - top) * sy)) if top else mh
    x1, y1 = max(x1, x0 + 1), max(y1, y0 + 1)
    boxes = boxes_in.copy()
    boxes[:, [0, 2]] = (boxes[:, [0, 2]] - left) / r
    boxes[:, [1, 3]] = (boxes[:, [1, 3]] - top) / r
    boxes[:, [0, 2]] = boxes[:, [0, 2]].clip(0, W)
    boxes[:, [1, 3]] = boxes[:, [1, 3]].clip(0, H)
    masks = np.zeros((len(m), H, W), bool)
    # upsample each mask only inside its box: the un-padded prototype crop [y0:y1, x0:x1] stretched to
    # H×W (bilinear, pixel centres), sampled by an inverse affine map over the box's pixels
    kx, ky = (x1 - x0) / W, (y1 - y0) / H
    for i in range(len(m)):
        bx0, by0, bx1, by1 = boxes[i]
        bx0, by0 = int(np.floor(bx0)), int(np.floor(by0))
        bx1, by1 = int(np.ceil(bx1)), int(np.ceil(by1))
        if bx1 <= bx0 or by1 <= by0:
            continue
        M = np.array([[kx, 0.0, (bx0 + 0.5) * kx - 0.5 + x0], [0.0, ky, (by0 + 0.5) * ky - 0.5 + y0]], np.float64)
        patch = cv2.warpAffine(m[i], M, (bx1 - bx0, by1 - by0), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_REPLICATE)
        masks[i, by0:by1, bx0:bx1] = patch > mask_thres
    return boxes.astype(np.float32), score.astype(np.float32), cls.astype(np.int64), masks


def _not_yolo_seg(session, path, why: str) -> DynslamError:
    return DynslamError(f"yolo-seg segmenter (motion.segmenter_model): {path} is not a YOLOv8-seg-format model "
                        f"({why}): it has {describe_io(session)}; expected {EXPECTED_IO}")


def check_outputs(session, path) -> None:
    """The model's declared inputs and outputs must be those of a YOLOv8-seg export (symbolic
    dimensions pass; the arrays are checked again on the first frame)."""
    check_image_input(session, path, "yolo-seg segmenter (motion.segmenter_model)", EXPECTED_IO)
    outs = session.get_outputs()
    if len(outs) < 2:
        raise _not_yolo_seg(session, path, f"{len(outs)} output{'s' if len(outs) != 1 else ''}, not 2")
    s0, s1 = list(outs[0].shape or []), list(outs[1].shape or [])
    if len(s0) != 3 or len(s1) != 4:
        raise _not_yolo_seg(session, path, f"outputs of rank {len(s0)} and {len(s1)}, not 3 and 4")
    nm, ch = fixed(s1[1]), fixed(s0[1])
    if nm is not None and ch is not None and ch < 4 + 1 + nm:
        raise _not_yolo_seg(session, path, f"output0 has {ch} channels, too few for 4 box values, a class "
                                           f"score and {nm} mask coefficients")


def check_output_arrays(out0: np.ndarray, protos: np.ndarray, path) -> None:
    """The arrays of one inference, for models whose declared shapes are symbolic."""
    if out0.ndim != 3 or protos.ndim != 4 or out0.shape[0] != 1 or protos.shape[0] != 1 \
            or out0.shape[1] < 5 + protos.shape[1]:
        raise DynslamError(f"yolo-seg segmenter (motion.segmenter_model): {path} returned arrays "
                           f"{'×'.join(map(str, out0.shape))} and {'×'.join(map(str, protos.shape))}; "
                           f"expected {EXPECTED_IO}")


class YoloSegSegmenter:
    """Any ONNX model with YOLOv8-seg outputs (YOLOv8-seg with 80 COCO classes, FastSAM with 1)."""

    name = "yolo-seg"

    def __init__(self, model_path: str, conf: float = 0.25, iou: float = 0.7, imgsz: int = IMGSZ,
                 prune_ratio: float = PRUNE_RATIO, min_area: int = MIN_INSTANCE_AREA, max_det: int = 100,
                 threads: int = 0, device: str = "cpu"):
        path = require_model(model_path, "yolo-seg segmenter (motion.segmenter_model)", FASTSAM_RECIPE)
        self.session = ort_session(path, threads, device)
        self.path = path
        check_outputs(self.session, path)
        inp = self.session.get_inputs()[0]
        self.input_name = inp.name
        shape = inp.shape
        h = shape[2] if len(shape) == 4 and isinstance(shape[2], int) else imgsz
        w = shape[3] if len(shape) == 4 and isinstance(shape[3], int) else imgsz
        self.input_hw = (int(h), int(w))
        self.conf, self.iou, self.max_det = conf, iou, max_det
        self.prune_ratio, self.min_area = prune_ratio, min_area
        meta = self.session.get_modelmeta().custom_metadata_map or {}
        try:
            self.names = {int(k): v for k, v in ast.literal_eval(meta.get("names", "{}")).items()}
        except (ValueError, SyntaxError):
            self.names = {}

    @classmethod
    def from_config(cls, mcfg, threads: int = 0, device: str = "cpu") -> "YoloSegSegmenter":
        return cls(mcfg.segmenter_model, conf=mcfg.segmenter_conf, iou=mcfg.segmenter_iou, threads=threads,
                   device=device)

    def detect(self, rgb: np.ndarray):
        """Boxes, scores, classes and full-resolution masks before pruning."""
        img, r, pad = letterbox(rgb, self.input_hw)
        x = np.ascontiguousarray(img.transpose(2, 0, 1)[None], dtype=np.float32) / 255.0
        out0, protos = self.session.run(None, {self.input_name: x})[:2]
        check_output_arrays(out0, protos, self.path)
        return decode(out0, protos, rgb.shape[:2], self.input_hw, r, pad, self.conf, self.iou,
                      True, self.max_det)

    def segment(self, rgb: np.ndarray, depth: Optional[np.ndarray] = None) -> Segmentation:
        boxes, scores, classes, masks = self.detect(rgb)
        h, w = rgb.shape[:2]
        if len(masks) == 0:
            return Segmentation.empty(h, w)
        kept = prune_parts(masks, self.prune_ratio)
        ids, src = masks_to_ids(masks[kept], self.min_area)
        src = kept[src]
        return Segmentation(ids, classes[src], scores[src])
