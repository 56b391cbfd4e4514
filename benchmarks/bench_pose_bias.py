"""Bias of the backend's pose-only solve on a synthetic scene (a diagnostic, no timing).

The backend runs alone over a scene rendered by ``dynslam synth`` (its ground-truth motion masks as the static
masks), with every tracked pose replaced by the ground truth: keyframes, landmarks and bundle adjustments are made
as usual, from right poses.  Then every frame the backend kept matches for is solved again pose-only against the
finished map (``tracking.optimize_pose``, as tracking and ``refine.refine_poses`` solve), starting at its
ground-truth pose.  Prints, per ``--huber``: the mean and median error of those solves in each frame's camera
frame (x right, y down, z forward; mm), the share of matches beyond the Huber kernel at the true pose, and what
those matches are (with depth, on a depth discontinuity, pyramid level, their mean residual and its radial part);
then, for every match with depth, the observed depth minus the landmark's depth in the frame at its true pose, by
how much of the keypoint's depth standard deviation its surface's slope makes (``depth_skew``).
``--map created`` solves against the landmarks as first created (the local bundle adjustment a no-op).

docs/experiments.md (sections "Bonn's depth in metres ..." and the one after it) found the solves stepping back
from what they look at on a map made from right poses, that the step is in the map (its landmarks sit nearer the
cameras than the frames see them) and is carried by the matches on steep depth slopes, and that removing it does
not lengthen the paths the backend tracks itself: the step back measured here is not their shortfall.

    dynslam synth static --out /tmp/static_dn0 --frames 120 --set synth.depth_noise=0 --set synth.depth_holes=0
    .venv/bin/python benchmarks/bench_pose_bias.py --seq /tmp/static_dn0 --k 0.002 --huber 2.8,1000
    .venv/bin/python benchmarks/bench_pose_bias.py --seq /tmp/static_dn0 --k 0.002 --huber 2.8 --map created
    .venv/bin/python benchmarks/bench_pose_bias.py              # synth/static as rendered by default (150 frames)
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np


def ground_truth_backend(spec: str, k: float | None, bundle: bool = True):
    """The backend after the sequence ``spec`` with every tracked pose set to the ground truth (relative to
    frame 0), not fused with the motion model's prediction; returns it, the sequence, the relative ground-truth
    poses and each frame's depth.  ``bundle`` False: the local bundle adjustment moves nothing (the landmarks
    stay where they were first created, from right poses)."""
    import dynslam_cli.backend.backend as bk
    from dynslam_cli.backend.bundle import BundleResult
    from dynslam_cli.backend.config import BackendConfig
    from dynslam_cli.data.open import open_sequence

    seq = open_sequence(spec)
    if any(p is None for p in seq.gt_poses):
        raise SystemExit(f"{spec}: every frame needs a ground-truth pose")
    g0 = np.linalg.inv(seq.gt_poses[0])
    gt = [g0 @ p for p in seq.gt_poses]
    current = {}
    real = bk.track_frame

    def track_at_truth(*a, **kw):
        tr = real(*a, **kw)
        return tr if tr.lost else dataclasses.replace(tr, pose=current["pose"].copy())

    intr = seq.intrinsics
    be = bk.Backend((intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height), BackendConfig(),
                    depth_noise=seq.depth_noise if k is None else k)
    depths = {}
    fuse = bk.Backend._fuse
    real_ba = bk.local_bundle_adjustment

    def fuse_at_truth(self, tr, kp, redo=False):  # the motion model sees the pose but does not move it
        fuse(self, tr, kp, redo)
        return tr.pose.copy()

    def no_bundle(cam, poses, optimise, fixed, ids, pos, obs_kf, *a, **kw):
        return BundleResult({int(q): poses[int(q)] for q in optimise}, ids, pos, np.zeros(len(obs_kf), bool),
                            0.0, 0.0, 0.0)

    bk.track_frame, bk.Backend._fuse = track_at_truth, fuse_at_truth
    if not bundle:
        bk.local_bundle_adjustment = no_bundle
    try:
        for f in seq:
            current["pose"] = gt[f.index]
            static = None if f.dynamic_mask is None else ~f.dynamic_mask
            be.track(f.index, f.rgb, f.depth, static, stamp=f.timestamp)
            depths[f.index] = f.depth
    finally:
        bk.track_frame, bk.Backend._fuse, bk.local_bundle_adjustment = real, fuse, real_ba
    return be, seq, gt, depths


def usable_matches(be, row: int) -> tuple[np.ndarray, np.ndarray, object]:
    """Frame ``row``'s kept matches to landmarks still alive and not found to move: (their rows among the frame's
    keypoints, the landmark ids, the frame's keypoints)."""
    ids, kp = be.matches.get(row)
    ok = ids >= 0
    ok[ok] = (be.lm.alive & ~be.lm.moving)[ids[ok]]
    r = np.flatnonzero(ok)
    return r, ids[r], kp


def solve_bias(be, gt, depths, huber: float) -> dict:
    """Each matched frame solved pose-only from its true pose against the finished map (see the module doc)."""
    from dynslam_cli.backend.features import on_depth_discontinuity
    from dynslam_cli.backend.tracking import CHI2_MONO, CHI2_STEREO, chi2, optimize_pose, stereo_residuals
    from dynslam_cli.geometry.camera import pixel_index

    cx, cy = be.cam.cx, be.cam.cy
    errs, rows_out, n_matches = [], [], 0
    for row in be.matches.frames():
        r, lm, kp = usable_matches(be, row)
        if len(r) < be.cfg.min_matches:
            continue
        X, kps = be.lm.pos[lm], kp.subset(r)
        n_matches += len(r)
        T, _ = optimize_pose(be.cam, gt[row], X, kps, huber)
        errs.append(gt[row][:3, :3].T @ (T[:3, 3] - gt[row][:3, 3]) * 1000)
        Tcw = np.linalg.inv(gt[row])
        _, e = stereo_residuals(be.cam, Tcw, X, kps.uv, kps.depth)
        c2 = chi2(be.cam, Tcw, X, kps.uv, kps.depth, kps.octave, kps.dsig)  # whitened as the solve whitens
        st = kps.depth > 0
        th = np.where(st, huber ** 2, huber ** 2 * CHI2_MONO / CHI2_STEREO)
        v, u = pixel_index(kps.uv, *depths[row].shape)
        occ = on_depth_discontinuity(depths[row], v, u, kps.octave)
        out = np.flatnonzero(c2 > th)
        d = kps.uv[out] - [cx, cy]
        radial = (e[out, 0] * d[:, 0] + e[out, 1] * d[:, 1]) / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1.0)
        rows_out.append(np.c_[kps.octave[out], st[out], occ[out], e[out, :2], radial])
    errs = np.array(errs).reshape(-1, 3)
    o = np.concatenate(rows_out) if rows_out else np.zeros((0, 6))
    return {"frames": len(errs), "mean": errs.mean(0) if len(errs) else np.full(3, np.nan),
            "median": np.median(errs, 0) if len(errs) else np.full(3, np.nan), "matches": n_matches,
            "beyond": len(o), "outliers": o}


# bins of a keypoint's depth standard deviation over the sensor's own (depth_sigma's slope term against k d^2)
SLOPE_BINS = (1.05, 1.5, 3.0, np.inf)


def depth_skew(be, gt, frames=None) -> list[dict]:
    """Each match with depth at the frame's true pose: the observed depth minus the landmark's depth in that
    camera (mm), by how much of the keypoint's depth standard deviation its surface's slope makes
    (``dsig / (k d^2)``, :data:`SLOPE_BINS`; 1 = the sensor's noise alone).  Rows: ``lo``, ``hi``, ``n``,
    ``mean`` and ``median`` (mm) over the matches within 5 cm, and their share of all matches.  ``frames``:
    the frames to take (default every frame the backend kept matches for)."""
    from dynslam_cli.backend.features import project

    k = be.detector.depth_noise
    dz, ratio = [], []
    for row in (be.matches.frames() if frames is None else frames):
        r, lm, kp = usable_matches(be, row)
        has = kp.depth[r] > 0
        r, lm = r[has], lm[has]
        _, z = project(gt[row], be.lm.pos[lm], be.cam.K)
        dz.append((kp.depth[r] - z) * 1000)
        ratio.append(kp.dsig[r] / np.maximum(k * kp.depth[r] ** 2, 1e-12))
    dz = np.concatenate(dz) if dz else np.zeros(0)
    ratio = np.concatenate(ratio) if ratio else np.zeros(0)
    near = np.abs(dz) < 50
    rows = []
    for lo, hi in zip((0.0,) + SLOPE_BINS[:-1], SLOPE_BINS, strict=True):
        m = near & (ratio >= lo) & (ratio < hi)
        rows.append({"lo": lo, "hi": hi, "n": int(m.sum()), "share": float(m.sum() / max(len(dz), 1)),
                     "mean": float(dz[m].mean()) if m.any() else float("nan"),
                     "median": float(np.median(dz[m])) if m.any() else float("nan")})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seq", default="synth/static",
                    help="a synthetic scene folder, or synth/PRESET (rendered into the data root; default synth/static)")
    ap.add_argument("--k", type=float, default=None, help="the backend's depth noise per m² (default: the scene's)")
    ap.add_argument("--huber", default="2.8,1000", help="comma-separated Huber widths (px) of the solve")
    ap.add_argument("--map", choices=("adjusted", "created"), default="adjusted",
                    help="the map the frames are solved against: after the local bundle adjustments (as the backend "
                         "runs) or the landmarks as first created from the right poses (bundle adjustment a no-op)")
    args = ap.parse_args()
    be, seq, gt, depths = ground_truth_backend(args.seq, args.k, bundle=args.map == "adjusted")
    print(f"{seq.name}: {len(seq)} frames, {len(be.kf_frame)} keyframes, {be.lm.n_alive} landmarks")
    print("| huber px | frames | solved - true, camera frame, mean mm (x y z) | median mm | matches | beyond the "
          "kernel at the truth | with depth | on a depth step | mean level | mean residual u, v px | radial px |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for h in (float(x) for x in args.huber.split(",")):
        r = solve_bias(be, gt, depths, h)
        o = r["outliers"]
        share = f"{r['beyond']} ({100 * r['beyond'] / max(r['matches'], 1):.1f} %)"
        if len(o):
            desc = (f"{o[:, 1].mean():.2f} | {o[:, 2].mean():.2f} | {o[:, 0].mean():.2f} | "
                    f"{o[:, 3].mean():.2f}, {o[:, 4].mean():.2f} | {o[:, 5].mean():.2f}")
        else:
            desc = "– | – | – | – | –"
        fmt = lambda a: " ".join(f"{x:+.3f}" for x in a)  # noqa: E731
        print(f"| {h:g} | {r['frames']} | {fmt(r['mean'])} | {fmt(r['median'])} | {r['matches']} | {share} | {desc} |")
    print("\nobserved - landmark depth at the true pose, matches within 5 cm, by the keypoint's depth sigma over k d^2:")
    print("| sigma / k d^2 | matches | share | mean mm | median mm |")
    print("|---|---|---|---|---|")
    for q in depth_skew(be, gt):
        print(f"| {q['lo']:g}-{q['hi']:g} | {q['n']} | {100 * q['share']:.1f} % | {q['mean']:+.3f} | {q['median']:+.3f} |")


if __name__ == "__main__":
    main()
