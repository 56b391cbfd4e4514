"""The keyframe bundle-adjustment backend alone (no neural map) over RGB-D sequences.

Prints one row per (sequence, static mask): ATE RMSE of the online poses, of the final
trajectory (frames composed with their bundle-adjusted reference keyframes), of that trajectory with
every frame but the keyframes solved again against the finished map (backend/refine.py) and of the
latter with its centres smoothed (as a run writes traj_est.txt: backend/smoothing.py), the Sim(3) scale
of that trajectory (estimate to ground truth: above 1 = the estimated path is too short) beside the
ATE of a camera that never moves, frames lost, keyframes, median ms per frame for tracking and per keyframe
for bundle adjustment, landmarks at the end.

    .venv/bin/python benchmarks/bench_backend.py --seqs bonn --masks none,yolo
    .venv/bin/python benchmarks/bench_backend.py --seqs /tmp/bk/static,/tmp/bk/walker --masks gt
    .venv/bin/python benchmarks/bench_backend.py --seqs bonn --masks yolo --set window=6 --depth full

Sequences: ``bonn`` (../shared/data/bonn_crowd_150_449_s2 with configs/bonn.yaml), or a folder
(a synthetic scene rendered by ``dynslam synth``, a TUM/Bonn folder).  Masks: ``none`` (all
pixels), ``gt`` (the ground-truth motion masks of synthetic scenes), ``yolo`` (people found by
../shared/models/yolov8n-seg_deq_fp32.onnx, dilated 5 px), ``run:DIR`` (the motion masks a
``dynslam run --save-masks`` wrote into DIR/masks/, dilated by motion.mask_dilation as the run
dilated them: the backend on exactly the masks the system gave it, without the system's wiring).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("DYNSLAM_SHARED", REPO.parent / "shared"))
BONN = SHARED / "data" / "bonn_crowd_150_449_s2"
YOLO = SHARED / "models" / "yolov8n-seg_deq_fp32.onnx"


def person_masker(dilate: int = 5):
    """rgb -> H×W bool: pixels of COCO people (class 0), dilated ``dilate`` px."""
    import cv2

    from dynslam_cli.motion.segment_yolo import YoloSegSegmenter

    seg = YoloSegSegmenter(str(YOLO))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate + 1, 2 * dilate + 1))

    def mask(rgb: np.ndarray) -> np.ndarray:
        _, _, classes, masks = seg.detect(rgb)
        people = np.asarray(masks)[np.asarray(classes) == 0] if len(masks) else []
        out = np.zeros(rgb.shape[:2], np.uint8)
        for m in people:
            out |= np.asarray(m, bool).astype(np.uint8)
        return cv2.dilate(out, kernel) > 0

    return mask


def run_dilation(run_dir: Path, default: float) -> float:
    """motion.mask_dilation of the run (its saved config.yaml), else ``default``."""
    from dynslam_cli.eval.runs import read_run_config

    motion = read_run_config(run_dir).get("motion") or {}
    return float(motion.get("mask_dilation", default))


def run_masker(folder: Path, dilation: float):
    """stamp -> H×W bool: the saved motion mask of that frame, dilated as the run dilated it."""
    import cv2

    from dynslam_cli.motion.module import dilation_radius

    if not folder.is_dir():
        raise SystemExit(f"no saved masks in {folder} (run dynslam run --save-masks)")

    def mask(stamp: str) -> np.ndarray:
        m = cv2.imread(str(folder / f"{stamp}.png"), cv2.IMREAD_GRAYSCALE)
        if m is None:
            raise SystemExit(f"missing mask {folder / (stamp + '.png')}")
        r = dilation_radius(dilation, m.shape[1])
        return cv2.dilate((m > 0).astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0

    return mask


def run_case(spec: str, masks: str, sets: list[str], depth_kind: str, frames: int | None,
             depth_noise: float | None = None) -> dict:
    from dynslam_cli.backend.backend import Backend
    from dynslam_cli.backend.config import BackendConfig
    from dynslam_cli.backend.smoothing import smooth_poses
    from dynslam_cli.config.loader import parse_override
    from dynslam_cli.config.resolve import resolve_config
    from dynslam_cli.data.open import open_sequence
    from dynslam_cli.eval.ate import compute_ate
    from dynslam_cli.run.runner import write_tum

    path = BONN if spec == "bonn" else Path(spec)
    cfg = resolve_config(str(path), frames=frames)
    seq = open_sequence(str(path), cfg)
    bcfg = BackendConfig()
    for s in sets:
        keys, value = parse_override(s)
        bcfg = dataclasses.replace(bcfg, **{keys[-1]: type(getattr(bcfg, keys[-1]))(value)})
    k = seq.intrinsics
    noise = seq.depth_noise if depth_noise is None else depth_noise
    be = Backend((k.fx, k.fy, k.cx, k.cy, k.width, k.height), bcfg, depth_noise=noise)
    masker = None  # frame -> H×W bool, True where something moves
    if masks == "yolo":
        people = person_masker()
        masker = lambda f: people(f.rgb)  # noqa: E731
    elif masks.startswith("run:"):
        saved = run_masker(Path(masks[4:]) / "masks", run_dilation(Path(masks[4:]), cfg.motion.mask_dilation))
        masker = lambda f: saved(seq.stamps[f.index])  # noqa: E731
    online, track_ms, ba_ms, lost, events = [], [], [], 0, []
    mask_ms = []
    for f in seq:
        static = None
        if masks == "gt":
            if f.dynamic_mask is None:
                raise SystemExit(f"{spec} has no ground-truth motion masks (--masks gt)")
            static = ~f.dynamic_mask
        elif masker is not None:
            t0 = time.perf_counter()
            static = ~masker(f)
            mask_ms.append((time.perf_counter() - t0) * 1000)
        depth = f.depth_full if depth_kind == "full" and f.depth_full is not None else f.depth
        out = be.track(f.index, f.rgb, depth, static, stamp=f.timestamp)
        online.append(out.pose_c2w)
        track_ms.append(out.track_ms)
        if out.keyframe and out.ba_ms > 0:
            ba_ms.append(out.ba_ms)
        if out.lost:
            lost += 1
            events.append(f"{f.index}: {out.reason}")
    with tempfile.TemporaryDirectory() as tmp:
        ates = {}
        final = be.trajectory()
        refined, _ = be.refined_trajectory()
        smoothed, _ = smooth_poses(seq.timestamps[:len(refined)], refined)  # as a run writes it
        for name, poses in (("online", np.stack(online)), ("final", final), ("refined", refined),
                            ("smoothed", smoothed)):
            est = write_tum(Path(tmp) / f"{name}.txt", seq.stamps, poses)
            ates[name] = compute_ate(est, seq.groundtruth_file)
        scale = compute_ate(Path(tmp) / "smoothed.txt", seq.groundtruth_file, align="sim3").scale
    return {"seq": path.name, "masks": masks, "frames": len(seq),
            "ate_cm": 100 * ates["online"].rmse_m, "ate_final_cm": 100 * ates["final"].rmse_m,
            "ate_refined_cm": 100 * ates["refined"].rmse_m, "ate_smoothed_cm": 100 * ates["smoothed"].rmse_m,
            "scale": scale, "max_cm": 100 * ates["final"].max_m, "still_cm": 100 * ates["final"].rmse_still_m,
            "lost": lost, "keyframes": len(be.kf_frame),
            "track_ms": float(np.median(track_ms)), "ba_ms": float(np.median(ba_ms)) if ba_ms else 0.0,
            "ba_max_ms": float(np.max(ba_ms)) if ba_ms else 0.0, "landmarks": be.lm.n_alive,
            "mask_ms": float(np.median(mask_ms)) if mask_ms else 0.0, "events": events}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seqs", default="bonn", help="comma-separated: bonn or sequence folders")
    ap.add_argument("--masks", default="none,yolo", help="comma-separated, of none, gt, yolo, run:DIR")
    ap.add_argument("--set", action="append", default=[], help="BackendConfig override key=value (repeatable)")
    ap.add_argument("--depth", choices=("cut", "full"), default="cut",
                    help="depth as the config cuts it (data.max_depth) or all of it")
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--depth-noise", type=float, default=None,
                    help="the depth noise per metre^2 the backend assumes (default: the sequence's own)")
    ap.add_argument("--events", action="store_true", help="print the lost frames")
    a = ap.parse_args()
    rows = []
    for spec in a.seqs.split(","):
        if spec == "bonn" and not BONN.is_dir():
            print(f"skipping bonn: {BONN} is absent", file=sys.stderr)
            continue
        for masks in a.masks.split(","):
            if masks == "yolo" and not YOLO.is_file():
                print(f"skipping yolo masks: {YOLO} is absent", file=sys.stderr)
                continue
            r = run_case(spec, masks, a.set, a.depth, a.frames, a.depth_noise)
            rows.append(r)
            print(f"done {r['seq']} {masks}", file=sys.stderr, flush=True)
            if a.events:
                for e in r["events"]:
                    print("  lost", e, file=sys.stderr)
    noise = "the sequence's" if a.depth_noise is None else f"{a.depth_noise:g}"
    print(f"settings: {' '.join(a.set) or 'defaults'}, depth {a.depth}, depth noise {noise}")
    cols = ("seq", "masks", "frames", "ate_cm", "ate_final_cm", "ate_refined_cm", "ate_smoothed_cm", "scale", "max_cm",
            "still_cm", "lost", "keyframes", "track_ms", "ba_ms", "ba_max_ms", "landmarks", "mask_ms")
    print(" | ".join(cols))
    for r in rows:
        print(" | ".join(f"{r[c]:.4f}" if c == "scale" else f"{r[c]:.2f}" if isinstance(r[c], float) else str(r[c])
                         for c in cols))


if __name__ == "__main__":
    main()
