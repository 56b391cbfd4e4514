"""The geometric segmenter: its time per frame and the mask IoU it allows at best, per working width.

    .venv/bin/python benchmarks/bench_segment.py                       # kidnap + walker 640x480 (rendered), Bonn
    .venv/bin/python benchmarks/bench_segment.py --seqs /data/synth/kidnap_s0 --widths 320,480,640 --step 2

Runs the segmenter a run uses (``motion.segmenter: geometric``, the sequence's intrinsics and depth,
``--widths`` overriding ``motion.geometric_width``) on every ``--step``-th frame, one thread, and
prints per sequence and width: segments per frame and ms per frame (medians), and, where the
sequence has ground-truth motion masks (synthetic scenes), the **oracle mask IoU**: each segment
called dynamic when most of its pixels are, its extent masked (what a run masks), the IoU with the
ground truth averaged over the frames
with a mover (as ``eval-masks`` averages a run's masks). No classifier can do better with these
segments: it is the segmenter's cap on a run's mask IoU.

Sequences: ``bonn`` (../shared/data/bonn_crowd_150_449_s2; timing only), a synthetic preset name
(``kidnap``, ``walker``, ...: rendered at 640x480 with ``--frames`` frames under --data-root on
first use and reused), or a sequence folder.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("DYNSLAM_SHARED", REPO.parent / "shared"))
BONN = SHARED / "data" / "bonn_crowd_150_449_s2"
PRESETS = ("static", "walker", "crowd", "kidnap", "balloon", "tracking")


def oracle_mask(ids: np.ndarray, gt: np.ndarray, extent: np.ndarray | None = None) -> np.ndarray:
    """H×W bool: the segments of ``ids`` (H×W int, 0 = none) with more than half of their pixels
    dynamic in ``gt`` (H×W bool), over their ``extent`` (H×W int, what a dynamic segment masks:
    ``Segmentation.extent``) where given, else over ``ids``."""
    n = int(max(ids.max(), 0 if extent is None else extent.max())) + 1
    area = np.bincount(ids.ravel(), minlength=n)
    moving = np.bincount(ids.ravel(), weights=gt.ravel().astype(np.float64), minlength=n)
    dynamic = 2 * moving > area
    dynamic[0] = False
    return dynamic[ids if extent is None else extent]


def sequence_path(spec: str, data_root: Path, frames: int) -> Path:
    """The folder of ``spec`` (bonn, a preset rendered on first use, or a folder)."""
    if spec == "bonn":
        if not BONN.is_dir():
            raise SystemExit(f"the Bonn clip is not at {BONN} (set DYNSLAM_SHARED or leave bonn out of --seqs)")
        return BONN
    if spec in PRESETS:
        path = data_root / f"bench-segment-{spec}-640x480-{frames}f"
        if not (path / "synth.json").is_file():
            from dynslam_cli.synth.config import SynthConfig
            from dynslam_cli.synth.render import render_preset

            render_preset(spec, path, SynthConfig(width=640, height=480, frames=frames, seed=0), progress=False)
        return path
    path = Path(spec)
    if not path.is_dir():
        raise SystemExit(f"no sequence folder {path} (and not bonn or a preset: {', '.join(PRESETS)})")
    return path


def measure(path: Path, widths: list[int], step: int) -> list[dict]:
    """One row per width: frames, segments and ms per frame (medians), oracle IoU (eval-masks' per-frame
    IoU; None without ground-truth masks)."""
    import cv2
    import torch

    from dynslam_cli.config.resolve import resolve_config
    from dynslam_cli.data.open import open_sequence
    from dynslam_cli.eval.masks import frame_scores
    from dynslam_cli.motion.segment_geometric import GeometricSegmenter

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    cfg = resolve_config(str(path))
    seq = open_sequence(str(path), cfg, progress=False)
    frames = [f for i, f in enumerate(seq) if i % step == 0]
    rows = []
    for w in widths:
        seg = GeometricSegmenter(seq.intrinsics, w)
        seg.segment(frames[0].rgb, frames[0].depth)  # numba's kernels load (or compile) once
        ms, counts, ious = [], [], []
        for f in frames:
            t0 = time.perf_counter()
            s = seg.segment(f.rgb, f.depth)
            ms.append((time.perf_counter() - t0) * 1000)
            counts.append(int(s.ids.max()))
            if f.dynamic_mask is not None and f.dynamic_mask.any():
                ious.append(frame_scores(oracle_mask(s.ids, f.dynamic_mask, s.extent), f.dynamic_mask)["iou"])
        rows.append({"seq": path.name, "width": w, "frames": len(frames), "segments": statistics.median(counts),
                     "ms": statistics.median(ms), "oracle_iou": float(np.mean(ious)) if ious else None})
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seqs", default="kidnap,walker,bonn", help="comma-separated: bonn, a preset, or folders")
    ap.add_argument("--widths", default="320,640", help="comma-separated working widths (motion.geometric_width)")
    ap.add_argument("--step", type=int, default=5, help="every STEP-th frame")
    ap.add_argument("--frames", type=int, default=150, help="frames of a preset rendered on first use")
    ap.add_argument("--data-root", default=str(Path(tempfile.gettempdir()) / "dynslam-bench-data"))
    a = ap.parse_args(argv)
    widths = [int(w) for w in a.widths.split(",")]
    print(f"{'sequence':<34} {'width':>5} {'frames':>6} {'segments':>8} {'ms':>7} {'oracle IoU':>10}")
    for spec in a.seqs.split(","):
        path = sequence_path(spec.strip(), Path(a.data_root), a.frames)
        for r in measure(path, widths, max(1, a.step)):
            oracle = "—" if r["oracle_iou"] is None else f"{r['oracle_iou']:.3f}"
            print(f"{r['seq']:<34} {r['width']:>5} {r['frames']:>6} {r['segments']:>8.0f} {r['ms']:>7.1f} {oracle:>10}",
                  flush=True)


if __name__ == "__main__":
    main()
