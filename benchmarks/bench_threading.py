"""Numba threading layers under load: one tracking step (render 1024 rays x 16 samples through the
neural map, loss, backward to the ray points with the table frozen) and one mapping step (2048
rays, table and decoders trainable), timed in a fresh process per threading layer: on an idle
machine, beside a plain busy-loop process, and beside a second dynslam-like process (the same
steps in a loop, 1 thread, same layer), as when two benchmarks run side by side.  Prints median /
min ms per step.

    .venv/bin/python benchmarks/bench_threading.py [--layers workqueue,omp] [--threads 1,2] [--reps 20]

dynslam uses workqueue unless NUMBA_THREADING_LAYER is set (dynslam_cli/utils/threads.py);
see README "Benchmarks" for the measured advice.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def worker(threads: int, reps: int) -> dict:
    """Runs in the child: times the two steps with the layer the environment selected."""
    sys.path.insert(0, str(REPO))
    import numba
    import torch

    from dynslam_cli.map.config import MapConfig
    from dynslam_cli.map.losses import ray_losses
    from dynslam_cli.map.model import NeuralMap
    from dynslam_cli.map.render import render_rays, sample_depths

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    cfg = MapConfig()
    model = NeuralMap(cfg, [[-2.6, -2.1, -0.1], [2.6, 2.1, 2.8]])
    gen = torch.Generator().manual_seed(0)

    def step(n_rays: int, train_map: bool) -> float:
        for p in model.parameters():
            p.requires_grad_(train_map)
        o = torch.zeros(1, 3, requires_grad=True)
        d = torch.nn.functional.normalize(torch.rand(n_rays, 3, generator=gen) - 0.5, dim=1)
        depth = 1 + 2 * torch.rand(n_rays, generator=gen)
        z = sample_depths(depth, cfg, gen)
        t0 = time.perf_counter()
        out = render_rays(model, o, d, z)
        loss = ray_losses(out, z, torch.rand(n_rays, 3, generator=gen), depth, cfg).total
        loss.backward()
        return 1e3 * (time.perf_counter() - t0)

    res = {}
    for name, n, train in (("track", 1024, False), ("map", 2048, True)):
        for _ in range(3):
            step(n, train)
        ts = [step(n, train) for _ in range(reps)]
        res[name] = (statistics.median(ts), min(ts))
    res["layer"] = numba.threading_layer()
    return res


def other_load(kind: str, env: dict) -> subprocess.Popen | None:
    """None, a busy Python loop, or a second process running the same steps endlessly."""
    if kind == "none":
        return None
    if kind == "busy loop":
        return subprocess.Popen([sys.executable, "-c", "while True: pass"])
    return subprocess.Popen([sys.executable, __file__, "--worker", "1", "100000"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layers", default="workqueue,omp")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--worker", nargs=2, type=int, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        print(json.dumps(worker(*a.worker)))
        return
    print(f"{'layer':<10} {'threads':>7} {'other load':<10} {'track ms':>9} {'(min)':>7} {'map ms':>8} {'(min)':>7}")
    for load in ("none", "busy loop", "2nd run"):
        for threads in (int(t) for t in a.threads.split(",")):
            for layer in a.layers.split(","):
                env = dict(os.environ, NUMBA_THREADING_LAYER=layer)
                hog = other_load(load, env)
                if hog is not None:
                    time.sleep(3)  # let the other load start
                try:
                    out = subprocess.run([sys.executable, __file__, "--worker", str(threads), str(a.reps)], env=env,
                                         capture_output=True, text=True, check=False)
                finally:
                    if hog is not None:
                        hog.kill()
                        hog.wait()
                if out.returncode != 0:
                    msg = out.stderr.strip().splitlines()[-1] if out.stderr.strip() else f"exit {out.returncode}"
                    print(f"{layer:<10} {threads:>7} {load:<10} unavailable: {msg}")
                    continue
                r = json.loads(out.stdout.strip().splitlines()[-1])
                print(f"{r['layer']:<10} {threads:>7} {load:<10} {r['track'][0]:>9.1f} "
                      f"{r['track'][1]:>7.1f} {r['map'][0]:>8.1f} {r['map'][1]:>7.1f}", flush=True)
    print(f"load average at end: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores (the idle rows assume "
          f"nothing else runs)")


if __name__ == "__main__":
    main()
