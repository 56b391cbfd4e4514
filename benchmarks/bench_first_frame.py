"""The first frame's map: time against quality for first-frame training budgets (iterations × rays).

For each budget and map seed, a fresh map is trained on frame 0 alone (``Mapper.optimize`` with
``first=True``, as a run's frame 0) and rendered without depth guidance at quarter resolution at
frames 0, 10, 20 and 40, at the poses the keyframe backend tracks for them (no masks; ground-truth
poses would do for synthetic scenes, but Bonn's are the motion-capture body's, not the camera's):
median and 90th percentile of |rendered − observed| depth, and the share of observed pixels the
map renders no surface for.  Frames 10–40 see parts frame 0 did not (the map extrapolates there) and, on dynamic
sequences, movers; the first checks of dynamic mode use this map.

    .venv/bin/python benchmarks/bench_first_frame.py                      # Bonn clip, 200x2048 / 200x1024 / 100x2048
    .venv/bin/python benchmarks/bench_first_frame.py --seq synth/static --budgets 200x2048,150x1024 --seeds 0,1

Sequences: ``bonn`` (../shared/data/bonn_crowd_150_449_s2; skipped with a message where absent),
or any ``--seq`` that ``dynslam run`` takes.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
BONN = Path(os.environ.get("DYNSLAM_SHARED", REPO.parent / "shared")) / "data" / "bonn_crowd_150_449_s2"
FRAMES = (0, 10, 20, 40)


def camera_poses(spec: str) -> tuple:
    """(the config, the sequence, camera-to-world poses of frames 0..max(FRAMES)) from the
    keyframe backend alone, tracking every frame on all pixels from the first frame's pose."""
    from dynslam_cli.backend.backend import Backend
    from dynslam_cli.config.resolve import resolve_config
    from dynslam_cli.data.open import open_sequence
    from dynslam_cli.slam.frontend import first_pose

    cfg = resolve_config(spec, None, ["mapping.first_iters=0", "run.mode=static"], frames=max(FRAMES) + 1)
    seq = open_sequence(spec, cfg, progress=False)
    k = seq.intrinsics
    be = Backend((k.fx, k.fy, k.cx, k.cy, k.width, k.height), first_pose=first_pose(seq[0]),
                 depth_noise=seq.depth_noise)
    for f in seq:
        full = f.depth_full if f.depth_full is not None else f.depth
        be.track(f.index, f.rgb, np.where(np.isfinite(full), full, 0).astype(np.float32), stamp=f.timestamp)
    return cfg, seq, be.trajectory()[: len(seq)].copy()


def measure(cfg, seq, poses: np.ndarray, iters: int, rays: int, seed: int) -> dict:
    import dataclasses

    import torch

    from dynslam_cli.run.runner import sequence_bounds
    from dynslam_cli.slam.system import SLAM

    cfg = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, seed=seed))
    slam = SLAM(cfg, seq.intrinsics, torch.device("cpu"), bounds=sequence_bounds(cfg, seq), depth_noise=seq.depth_noise)
    slam.track(seq[0])  # builds the map (nothing trained: first_iters=0)
    t0 = time.perf_counter()
    slam.mapper.optimize(slam.cur, iters, rays, first=True)
    out = {"iters": iters, "rays": rays, "seed": seed, "s": time.perf_counter() - t0}
    for j in FRAMES:
        if j >= len(seq):
            continue
        fj = seq[j]
        d, _ = slam.render(poses[j], 0.25)
        obs = np.asarray(fj.depth)[::4, ::4][: d.shape[0], : d.shape[1]]
        seen = obs > 0
        both = seen & (d > 0)
        e = np.abs(d[both] - obs[both]) * 100
        out[f"f{j}_med"] = float(np.median(e)) if len(e) else float("nan")
        out[f"f{j}_p90"] = float(np.percentile(e, 90)) if len(e) else float("nan")
        out[f"f{j}_hole"] = 100 * float((seen & (d <= 0)).sum()) / max(1, int(seen.sum()))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seq", default="bonn", help="bonn, or any sequence dynslam run takes")
    ap.add_argument("--budgets", default="200x2048,200x1024,100x2048", help="comma-separated ITERSxRAYS")
    ap.add_argument("--seeds", default="0", help="comma-separated map seeds (run.seed)")
    ap.add_argument("--threads", type=int, default=2, help="torch/numba threads")
    a = ap.parse_args()
    from dynslam_cli.utils.threads import set_threads

    set_threads(a.threads)
    spec = a.seq
    if spec == "bonn":
        if not BONN.is_dir():
            print(f"skipping: the Bonn clip is absent ({BONN}); pass --seq", file=sys.stderr)
            return
        spec = str(BONN)
    cfg, seq, poses = camera_poses(spec)
    rows = []
    for b in a.budgets.split(","):
        iters, rays = (int(x) for x in b.lower().split("x"))
        for seed in (int(s) for s in a.seeds.split(",")):
            rows.append(measure(cfg, seq, poses, iters, rays, seed))
            print(f"done {b} seed {seed}: {rows[-1]['s']:.1f} s", file=sys.stderr, flush=True)
    print(f"first-frame map of {Path(spec).name}, {a.threads} threads: |rendered - observed| depth (cm) at "
          f"the backend's poses, quarter resolution; hole = % of observed pixels without a rendered surface")
    cols = ["iters", "rays", "seed", "s"] + [f"f{j}_{m}" for j in FRAMES for m in ("med", "p90", "hole")]
    print(" | ".join(cols))
    for r in rows:
        print(" | ".join(f"{r[c]:.2f}" if isinstance(r.get(c), float) else str(r.get(c, "-")) for c in cols))


if __name__ == "__main__":
    main()
