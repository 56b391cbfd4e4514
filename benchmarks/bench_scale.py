"""Scale of the backend's pose-only tracking against known geometry (a diagnostic of a bias, no timing).

For frame pairs ``gap`` frames apart of a synthetic scene: landmarks are the first frame's ORB
keypoints back-projected with its depth at its ground-truth pose; the second frame is tracked
against them as the backend tracks (``search_by_projection`` + ``optimize_pose`` from the first
frame's pose).  Prints one row per (scene, depth noise assumed): the estimated translation along
the true one, as a ratio (1 = right length; below 1 = too short), median and mean over the pairs,
and the median position error.  The ``exact`` rows replace the keypoints by the landmarks' exact
projections plus ±0.3 px of uniform noise: the estimator itself, without feature noise.

    .venv/bin/python benchmarks/bench_scale.py                       # synth static, with and without sensor noise
    .venv/bin/python benchmarks/bench_scale.py --scenes /tmp/s/static --gap 30 --depth-noise 0.002,1

Scenes: folders rendered by ``dynslam synth`` (with ground truth); by default the ``static`` preset
(300 frames, 640x480) is rendered twice into a temporary folder: with the preset's sensor noise and
with none (``synth.depth_noise``, ``depth_holes``, ``rgb_noise`` 0).  ``--depth-noise``: the depth noise
per metre² the tracking assumes (comma-separated; ``seq`` = the scene's own; 1 = pixels only).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

CLEAN = ["synth.depth_noise=0", "synth.depth_holes=0", "synth.rgb_noise=0"]


def render(folder: Path, clean: bool) -> Path:
    from dynslam_cli.config.resolve import resolve_config
    from dynslam_cli.synth.render import render_preset

    cfg = resolve_config("synth/static", None, CLEAN if clean else [])
    render_preset("static", folder, cfg.synth, progress=False)
    return folder


def pairs_ratio(spec: str, gap: int, depth_noise: str, exact: bool, step: int = 7) -> dict:
    from dynslam_cli.backend.backend import Backend
    from dynslam_cli.backend.features import SCALE, Keypoints, backproject, project
    from dynslam_cli.backend.tracking import optimize_pose, search_by_projection
    from dynslam_cli.config.resolve import resolve_config
    from dynslam_cli.data.open import open_sequence

    seq = open_sequence(spec, resolve_config(spec))
    k = seq.intrinsics
    noise = seq.depth_noise if depth_noise == "seq" else float(depth_noise)
    be = Backend((k.fx, k.fy, k.cx, k.cy, k.width, k.height), depth_noise=noise)
    cam, det, huber = be.cam, be.detector, be.cfg.huber_px
    rng = np.random.default_rng(0)
    ratio, err = [], []
    for i in range(0, len(seq) - gap, step):
        a, b = seq[i], seq[i + gap]
        if a.pose_c2w is None or b.pose_c2w is None:
            raise SystemExit(f"{spec} has no ground-truth poses")
        Ta, Tb = np.asarray(a.pose_c2w, np.float64), np.asarray(b.pose_c2w, np.float64)
        ka = det.detect(a.rgb, a.depth)
        ka = ka.subset(ka.depth > 0)
        X = backproject(ka, cam.K, Ta)
        if exact:
            uv, z = project(Tb, X, cam.K)
            ok = (z > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < k.width) & (uv[:, 1] >= 0) & (uv[:, 1] < k.height)
            X, uv, z = X[ok], uv[ok] + rng.uniform(-0.3, 0.3, (int(ok.sum()), 2)), z[ok]
            kb = Keypoints(uv, np.zeros((len(z), 32), np.uint8), z, np.zeros(len(z), np.int64), noise * z * z + 1e-6)
        else:
            kb = det.detect(b.rgb, b.depth)
            la, lb, _ = search_by_projection(cam, Tb, X, ka.des, SCALE ** ka.octave.astype(float), kb, 15.0)
            X, kb = X[la], kb.subset(lb)
        if len(X) < 30:
            continue
        T, _ = optimize_pose(cam, Ta, X, kb, huber)
        d_true, d_est = Tb[:3, 3] - Ta[:3, 3], T[:3, 3] - Ta[:3, 3]
        n = float(np.linalg.norm(d_true))
        if n < 0.03:
            continue
        ratio.append(float(d_est @ d_true) / n ** 2)
        err.append(100 * float(np.linalg.norm(d_est - d_true)))
    return {"scene": Path(spec).name, "noise": noise, "kind": "exact" if exact else "orb", "pairs": len(ratio),
            "median": float(np.median(ratio)) if ratio else float("nan"),
            "mean": float(np.mean(ratio)) if ratio else float("nan"),
            "err_cm": float(np.median(err)) if err else float("nan")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default=None, help="comma-separated synthetic scene folders (default: render static "
                    "with and without sensor noise)")
    ap.add_argument("--gap", type=int, default=15, help="frames between the two frames of a pair")
    ap.add_argument("--depth-noise", default="seq,1", help="comma-separated: seq (the scene's own) or a number")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        if a.scenes:
            scenes = [Path(s) for s in a.scenes.split(",")]
        else:
            print("rendering synth static with and without sensor noise ...", file=sys.stderr, flush=True)
            scenes = [render(Path(tmp) / "static", False), render(Path(tmp) / "static_clean", True)]
        rows = []
        for s in scenes:
            for dn in a.depth_noise.split(","):
                for exact in (False, True):
                    rows.append(pairs_ratio(str(s), a.gap, dn, exact))
                    print(f"done {s.name} {dn} {'exact' if exact else 'orb'}", file=sys.stderr, flush=True)
    print(f"pose-only tracking over {a.gap} frames: estimated translation along the true one / its length")
    cols = ("scene", "kind", "noise", "pairs", "median", "mean", "err_cm")
    print(" | ".join(cols))
    for r in rows:
        print(" | ".join(f"{r[c]:.4f}" if isinstance(r[c], float) else str(r[c]) for c in cols))


if __name__ == "__main__":
    main()
