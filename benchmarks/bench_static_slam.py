"""Static SLAM benchmark: ATE RMSE (SE(3) Umeyama, associated by frame/timestamp) and fps.

Cases: ``synth`` (synth/static, 150 frames, 640x480) and ``bonn`` (frames 0-39 of
../shared/data/bonn_crowd_150_449_s2, before people enter), plus the ATE of a camera that never
moves on the same ground truth.  Prints a table; ``--json FILE`` also writes the numbers.

    .venv/bin/python benchmarks/bench_static_slam.py [--cases synth,bonn] [--threads N]
        [--set key=value ...] [--frames N]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

BONN = Path(os.environ.get("DYNSLAM_SHARED", REPO.parent / "shared")) / "data" / "bonn_crowd_150_449_s2"


def ate_rmse(est: np.ndarray, gt: np.ndarray) -> float:
    """Translation RMSE after the SE(3) Umeyama alignment of ``est`` onto ``gt`` (N×3 each)."""
    from dynslam_cli.geometry.align import apply_similarity, umeyama

    r, t, _ = umeyama(est, gt)
    return float(np.sqrt(((apply_similarity(est, r, t) - gt) ** 2).sum(1).mean()))


def run_case(name: str, spec: str, dataset: str, frames: int, sets: list[str], threads: int) -> dict:
    from dynslam_cli.config import load_config
    from dynslam_cli.data.names import identify
    from dynslam_cli.data.open import open_sequence
    from dynslam_cli.eval.ate import read_tum
    from dynslam_cli.run.runner import run_sequence

    sid = identify(spec)
    over = [f"data.frames={frames}", "run.mode=static", f"run.threads={threads}", "run.mesh=false",
            "run.checkpoint_every=0"] + sets
    cfg = load_config(sid.dataset, sid.name, None, over)
    seq = open_sequence(spec, cfg)
    gt = np.array([p[:3, 3] for p in seq.gt_poses])
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        res = run_sequence(spec, cfg, out_dir=Path(tmp) / "run", progress=False)
        wall = time.perf_counter() - t0
        stamps, est, _ = read_tum(res.out_dir / "traj_est.txt")
        timing = json.loads((res.out_dir / "timing.json").read_text())
    assert np.allclose(stamps, seq.timestamps, atol=1e-5)
    still = np.repeat(gt[:1], len(gt), 0)
    return {"case": name, "frames": len(gt), "ate_cm": 100 * ate_rmse(est, gt),
            "still_ate_cm": 100 * ate_rmse(still + 1e-12, gt), "fps": timing["fps"],
            "fps_after_first": timing["fps_after_first"], "first_frame_s": timing["first_frame_ms"] / 1000,
            "track_ms": timing["median_ms"]["track"], "wall_s": wall, "events": timing.get("events", 0)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="synth,bonn")
    ap.add_argument("--threads", type=int, default=0, help="torch/numba threads (0 = all cores)")
    ap.add_argument("--set", dest="sets", action="append", default=[], help="config override key=value")
    ap.add_argument("--frames", type=int, default=0, help="override the frame count of every case")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    cases = {
        "synth": ("synth/static", "synth", 150, ["synth.width=640", "synth.height=480", "synth.frames=150"]),
        "bonn": (str(BONN), "bonn", 40, []),
    }
    rows = []
    for name in a.cases.split(","):
        spec, ds, n, extra = cases[name]
        rows.append(run_case(name, spec, ds, a.frames or n, extra + a.sets, a.threads))
        r = rows[-1]
        print(f"{r['case']:6s} frames {r['frames']:4d}  ATE {r['ate_cm']:6.2f} cm  still {r['still_ate_cm']:6.2f} cm  "
              f"fps {r['fps']:5.2f} (after first {r['fps_after_first']:5.2f})  first {r['first_frame_s']:5.1f} s  "
              f"track {r['track_ms']:6.1f} ms  wall {r['wall_s']:6.1f} s", flush=True)
    print(f"load average at end: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; overrides: {a.sets}")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
