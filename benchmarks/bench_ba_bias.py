"""Bias of the backend's local bundle adjustment on simulated data (a diagnostic, no timing).

Random landmarks 2-5 m in front of a camera that moves ``--step`` per keyframe (lateral x and
forward z in the ratio 5:2), exact projections plus Gaussian noise: ``--px`` px on the pixel and
``k``·depth² m on the depth (``--noise``: comma-separated k), or the same noise put on the
disparity (``--on disparity``).  Landmarks start where the first keyframe's noisy observation puts
them (as the backend creates them), keyframes at their true poses; ``local_bundle_adjustment`` then
optimises all keyframes but the first (held) and every landmark seen twice.  Prints, per k, the
estimated translation of the last keyframe along the true one as a ratio (1 = right length; below
1 = too short): mean, median and spread over ``--seeds`` simulations.  The real backend's shrinkage on
synthetic scenes (docs/experiments.md) can be set beside what the estimator alone does at a given
noise.

    .venv/bin/python benchmarks/bench_ba_bias.py                              # k = 0.002, 0.005, 0.01
    .venv/bin/python benchmarks/bench_ba_bias.py --noise 0.01 --on disparity --seeds 20
"""

from __future__ import annotations

import argparse
import statistics

import numpy as np

FX, CX, CY, W, H = 525.0, 319.5, 239.5, 640, 480


def simulate(seed: int, k: float, px: float, on: str, keyframes: int, step: float, n: int = 600) -> float:
    from dynslam_cli.backend.bundle import local_bundle_adjustment
    from dynslam_cli.backend.tracking import Camera

    rng = np.random.default_rng(seed)
    cam = Camera(FX, FX, CX, CY, W, H, FX * 0.08)
    X = np.stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(2, 5, n)], 1)
    poses = {}
    for i in range(keyframes):
        T = np.eye(4)
        T[:3, 3] = np.array([1.0, 0.0, 0.4]) * step * i
        poses[i] = T
    cols = {c: [] for c in ("kf", "lm", "uv", "depth", "sig")}
    for i in range(keyframes):
        pc = X - poses[i][:3, 3]
        u = FX * pc[:, 0] / pc[:, 2] + CX
        v = FX * pc[:, 1] / pc[:, 2] + CY
        idx = np.flatnonzero((u >= 0) & (u < W) & (v >= 0) & (v < H))
        z = pc[idx, 2]
        if on == "disparity":
            d = cam.bf / (cam.bf / z + rng.normal(0, 1, len(idx)) * cam.bf * k)
        else:
            d = z + rng.normal(0, 1, len(idx)) * k * z * z
        cols["kf"].append(np.full(len(idx), i))
        cols["lm"].append(idx)
        cols["uv"].append(np.stack([u[idx], v[idx]], 1) + rng.normal(0, px, (len(idx), 2)))
        cols["depth"].append(d)
        cols["sig"].append(np.maximum(k * z * z, 1e-6))
    kf, lm, uv, depth, sig = (np.concatenate(cols[c]) for c in ("kf", "lm", "uv", "depth", "sig"))
    pos = X.copy()
    first = kf == 0
    d0, uv0 = depth[first], uv[first]
    pos[lm[first]] = np.stack([(uv0[:, 0] - CX) / FX * d0, (uv0[:, 1] - CY) / FX * d0, d0], 1)
    res = local_bundle_adjustment(cam, dict(poses), list(range(1, keyframes)), [0], np.arange(n), pos, kf, lm, uv,
                                  depth, np.zeros(len(kf), np.int64), sig, huber=2.8 * max(px, 1e-3))
    t_true = poses[keyframes - 1][:3, 3]
    t_est = res.poses[keyframes - 1][:3, 3]
    return float(t_est @ t_true / (t_true @ t_true))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--noise", default="0.002,0.005,0.01", help="comma-separated depth noise k (m per m^2)")
    ap.add_argument("--px", type=float, default=0.5, help="pixel noise (px, standard deviation)")
    ap.add_argument("--on", choices=("depth", "disparity"), default="depth", help="where the noise is Gaussian")
    ap.add_argument("--keyframes", type=int, default=5)
    ap.add_argument("--step", type=float, default=0.05, help="metres per keyframe along x (0.4 of it along z)")
    ap.add_argument("--seeds", type=int, default=10)
    a = ap.parse_args()
    print(f"local bundle adjustment, {a.keyframes} keyframes {a.step:g} m apart, pixel noise {a.px:g} px, depth "
          f"noise Gaussian in {a.on}: estimated / true translation of the last keyframe over {a.seeds} seeds")
    print("k | mean | median | min | max")
    for k in (float(x) for x in a.noise.split(",")):
        r = [simulate(s, k, a.px, a.on, a.keyframes, a.step) for s in range(a.seeds)]
        print(f"{k:g} | {statistics.mean(r):.4f} | {statistics.median(r):.4f} | {min(r):.4f} | {max(r):.4f}")


if __name__ == "__main__":
    main()
