"""Reusing an instance's embedding while its crop has not changed: how often, and how far from a fresh one.

    .venv/bin/python benchmarks/bench_encoder_reuse.py                          # the Bonn clip
    .venv/bin/python benchmarks/bench_encoder_reuse.py --seqs bonn,data/synth/walker_s0 --frames 150 --tau 2,4,8

Issue 21 asks whether encoding can be skipped for instances that did not change.  This measures it
without changing a run: every frame of each sequence is cut into the geometric segmenter's segments
and cropped as a run does (``motion.encoder_input_size`` 0: 160 px, the run's margin and fill), and
every crop is encoded fresh with the run's encoder (EfficientNet-Lite0 on onnxruntime).  Then, per
threshold ``tau``, a cache is replayed frame by frame: a crop whose thumbnail (the masked crop shrunk
to 20×20, colour) differs from a crop encoded within the last ``--age`` frames by less than ``tau``
grey levels on average takes that crop's embedding; any other crop is encoded and enters the cache.
Prints per sequence and ``tau``: the share of crops that would not be encoded, the cosine of a reused
embedding to the fresh one (minimum, 5th percentile, median), the share of reused crops below 0.95,
and the encoding time per frame it would leave (the median ms per crop, measured here, times the crops
still encoded).  The classifier's decisions are learnt online from these embeddings, so they cannot be
compared frame by frame; the cosine is the stand-in (bench_encoder.py uses the same).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("DYNSLAM_SHARED", REPO.parent / "shared"))
BONN = SHARED / "data" / "bonn_crowd_150_449_s2"
THUMB = 20


def thumbnails(crops: np.ndarray) -> np.ndarray:
    """(K, size, size, 3) uint8 crops -> (K, THUMB*THUMB*3) float32 thumbnails (area-averaged)."""
    import cv2

    return np.stack([cv2.resize(c, (THUMB, THUMB), interpolation=cv2.INTER_AREA).astype(np.float32).ravel()
                     for c in crops]) if len(crops) else np.zeros((0, THUMB * THUMB * 3), np.float32)


def replay(frames: list[tuple[np.ndarray, np.ndarray]], tau: float, age: int) -> tuple[np.ndarray, np.ndarray]:
    """Per crop of ``frames`` (a list, per frame, of (thumbnails K×T, fresh embeddings K×D)): whether it
    is reused and the embedding the cache gives it (its own fresh one where encoded)."""
    cache_t, cache_e, cache_f = [], [], []
    reused, given = [], []
    for fi, (th, emb) in enumerate(frames):
        keep = [i for i, f in enumerate(cache_f) if fi - f <= age]
        cache_t, cache_e, cache_f = [cache_t[i] for i in keep], [cache_e[i] for i in keep], [cache_f[i] for i in keep]
        ct = np.stack(cache_t) if cache_t else None
        new = []
        for k in range(len(th)):
            if ct is not None:
                d = np.abs(ct - th[k]).mean(1)
                j = int(np.argmin(d))
                if d[j] < tau:
                    reused.append(True)
                    given.append(cache_e[j])
                    continue
            reused.append(False)
            given.append(emb[k])
            new.append(k)
        for k in new:  # encoded crops enter the cache after the frame (a frame's crops do not reuse each other)
            cache_t.append(th[k])
            cache_e.append(emb[k])
            cache_f.append(fi)
    dim = frames[0][1].shape[1] if frames else 0
    return np.array(reused, bool), (np.array(given, np.float32) if given else np.zeros((0, dim), np.float32))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seqs", default="bonn", help="comma-separated: bonn or sequences dynslam run takes")
    ap.add_argument("--frames", type=int, default=0, help="frames of each sequence (0 = all)")
    ap.add_argument("--tau", default="1,2,4,8", help="comma-separated thumbnail thresholds (grey levels, mean abs)")
    ap.add_argument("--age", type=int, default=5, help="frames an encoded crop stays in the cache")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()

    import torch
    from _bench import segment_crops

    from dynslam_cli.motion.encode_effnet import MEAN, STD
    from dynslam_cli.motion.encode_base import normalise_batch
    from dynslam_cli.motion.encoders import make_encoder

    torch.set_num_threads(a.threads)
    taus = [float(t) for t in a.tau.split(",") if t]
    print("| sequence | crops / frame | tau | not encoded | cosine min / p5 / median | reused < 0.95 | encode ms / frame |")
    print("|---|---|---|---|---|---|---|")
    for name in [s for s in a.seqs.split(",") if s]:
        spec = str(BONN) if name == "bonn" else name
        if name == "bonn" and not BONN.is_dir():
            print(f"skipping the Bonn clip: {BONN} is absent (set DYNSLAM_SHARED)")
            continue
        per_frame, cfg = segment_crops(spec, frames=a.frames)
        enc = make_encoder(cfg.motion, a.threads)
        frames, ms = [], []
        for crops in per_frame:
            if len(crops) == 0:
                frames.append((np.zeros((0, THUMB * THUMB * 3), np.float32), np.zeros((0, enc.dim), np.float32)))
                continue
            t = time.perf_counter()
            f, _ = enc._run(normalise_batch(crops, MEAN, STD))
            ms.append((time.perf_counter() - t) * 1e3 / len(crops))
            f = f / np.linalg.norm(f, axis=1, keepdims=True)
            frames.append((thumbnails(crops), f.astype(np.float32)))
        fresh = np.concatenate([e for _, e in frames])
        n, per_crop = len(fresh), statistics.median(ms) if ms else float("nan")
        for tau in taus:
            reused, given = replay(frames, tau, a.age)
            cos = (given * fresh).sum(1)[reused]
            stats = (f"{cos.min():.3f} / {np.percentile(cos, 5):.3f} / {np.median(cos):.3f}" if len(cos) else "—")
            low = f"{(cos < 0.95).mean():.3f}" if len(cos) else "—"
            left = per_crop * (n - int(reused.sum())) / len(frames)
            print(f"| {name} | {n / len(frames):.1f} | {tau:g} | {reused.mean():.3f} | {stats} | {low} | "
                  f"{left:.0f} (all: {per_crop * n / len(frames):.0f}) |")


if __name__ == "__main__":
    main()
