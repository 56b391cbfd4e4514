"""Milliseconds per frame of each segmenter and encoder at 640×480 (median over repeats).

    .venv/bin/python benchmarks/bench_motion.py [--repeats 10] [--threads 0]

Inputs: a Bonn crowd frame (../shared/data/bonn_crowd_150_449_s2) when present, else the toy
scene; bus.jpg resized to 640×480 for yolo-seg (so that there is something to decode). Encoders
are timed on the geometric segmenter's instances of the frame (K is printed).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
SHARED = Path(os.environ.get("DYNSLAM_SHARED", REPO.parent / "shared"))


def timeit(fn, repeats: int) -> float:
    fn()  # warm-up
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t) * 1e3)
    return statistics.median(ts)


def load_frame():
    clip = SHARED / "data" / "bonn_crowd_150_449_s2"
    if (clip / "rgb.txt").is_file():
        rgbs = sorted((clip / "rgb").glob("*.png"))
        deps = sorted((clip / "depth").glob("*.png"))
        if rgbs and deps:
            i = min(60, len(rgbs) - 1)
            rgb = cv2.cvtColor(cv2.imread(str(rgbs[i])), cv2.COLOR_BGR2RGB)
            depth = cv2.imread(str(deps[i]), cv2.IMREAD_UNCHANGED).astype(np.float32) / 5000.0
            return rgb, depth, f"bonn crowd frame {rgbs[i].name}"
    from dynslam_cli.motion.toyscene import render_toy

    rgb, depth, _ = render_toy(640, 480, noise=0.003)
    return rgb, depth, "toy scene"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--threads", type=int, default=0, help="onnxruntime intra-op threads (0 = default)")
    args = ap.parse_args()
    os.environ.setdefault("DYNSLAM_CACHE", str(Path(tempfile.gettempdir()) / "dynslam-bench-cache"))

    from dynslam_cli.config import Config
    from dynslam_cli.motion.encoders import make_encoder
    from dynslam_cli.motion.segmenters import make_segmenter

    rgb, depth, what = load_frame()
    cfg = Config()
    cfg.run.threads = args.threads
    rows = []
    geo = make_segmenter(cfg.motion, threads=cfg.run.threads)
    seg = geo.segment(rgb, depth)
    rows.append(("segmenter", "geometric", what, seg.count, timeit(lambda: geo.segment(rgb, depth), args.repeats)))
    yolo = SHARED / "models" / "yolov8n-seg_deq_fp32.onnx"
    if yolo.is_file():
        bus = cv2.resize(cv2.cvtColor(cv2.imread(str(SHARED / "images" / "bus.jpg")), cv2.COLOR_BGR2RGB), (640, 480))
        for name in ("yolov8n-seg_deq_fp32.onnx", "yolov8n-seg_int8.onnx"):
            cfg.motion.segmenter, cfg.motion.segmenter_model = "yolo-seg", str(SHARED / "models" / name)
            ys = make_segmenter(cfg.motion, threads=cfg.run.threads)
            k = ys.segment(bus).count
            rows.append(("segmenter", f"yolo-seg ({name})", "bus.jpg 640×480", k,
                         timeit(lambda ys=ys: ys.segment(bus), args.repeats)))
            rows.append(("segmenter", f"yolo-seg ({name})", what, ys.segment(rgb).count,
                         timeit(lambda ys=ys: ys.segment(rgb), args.repeats)))
    else:
        print(f"(yolo-seg skipped: {yolo} absent)")
    ids = seg.ids
    for enc_name in ("effnet-lite0", "color-hist"):
        cfg.motion.encoder = enc_name
        enc = make_encoder(cfg.motion, threads=cfg.run.threads)
        label = enc_name + (f" [{enc.backend}]" if hasattr(enc, "backend") else "")
        rows.append(("encoder", label, what, seg.count, timeit(lambda enc=enc: enc.encode(rgb, ids), args.repeats)))
    from dynslam_cli.motion.encode_effnet import EffNetLite0Encoder

    enc = EffNetLite0Encoder(backend="torch")
    rows.append(("encoder", "effnet-lite0 [torch]", what, seg.count, timeit(lambda: enc.encode(rgb, ids), args.repeats)))

    # the whole observe + check on the frame (geometric + effnet), map = the frame pushed back 0.5 m on the left half
    import torch
    from types import SimpleNamespace

    from dynslam_cli.motion.module import MotionModule

    cfg = Config()
    cfg.run.threads = args.threads
    f = 525.0
    mod = MotionModule(cfg, (f, f, 319.5, 239.5), torch.device("cpu"))
    frame = SimpleNamespace(index=0, rgb=rgb, depth=depth)
    rendered = depth.copy()
    rendered[:, :320] += 0.5
    rendered = cv2.resize(rendered, (160, 120), interpolation=cv2.INTER_NEAREST)
    inst = mod.observe(frame, np.eye(4))
    rows.append(("module", "observe (geometric + effnet-lite0 + g)", what, inst.count,
                 timeit(lambda: mod.observe(frame, np.eye(4)), args.repeats)))
    init = mod.state_dict()
    upd, chk = [], []
    for _ in range(max(3, args.repeats // 2)):
        mod.load_state_dict(init)  # g untrained again: the check contradicts it → an update
        inst = mod.observe(frame, np.eye(4))
        t = time.perf_counter()
        rec = mod.check_and_update(frame, inst, np.eye(4), rendered, None)
        upd.append((time.perf_counter() - t) * 1e3)
        inst = mod.observe(frame, np.eye(4))
        t = time.perf_counter()
        mod.check_and_update(frame, inst, np.eye(4), rendered, None)  # g agrees now: check only
        chk.append((time.perf_counter() - t) * 1e3)
    rows.append(("module", f"check_and_update with an update ({rec.steps if rec else 0} Adam steps)", what,
                 inst.count, statistics.median(upd)))
    rows.append(("module", "check_and_update, check only (bidirectional)", what, inst.count, statistics.median(chk)))

    print(f"\nmotion components at 640×480, median of {args.repeats} runs, {os.cpu_count()} CPU cores, "
          f"ORT threads {args.threads or 'default'}\n")
    print("| part | name | input | K | ms/frame |\n|---|---|---|---:|---:|")
    for part, name, inp, k, ms in rows:
        print(f"| {part} | {name} | {inp} | {k} | {ms:.1f} |")


if __name__ == "__main__":
    main()
