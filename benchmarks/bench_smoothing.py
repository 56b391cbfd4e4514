"""The trajectory smoother judged on finished runs, without running them again.

A run of the keyframe backend writes ``traj_unsmoothed.txt`` (every frame solved again against the finished map)
and smooths its camera centres into ``traj_est.txt`` (``backend/smoothing.py``); the smoother reads nothing else.
So a change to the smoother can be measured exactly on stored run folders: for each, this prints the ATE (cm,
SE(3), against the ground truth its run.json names) of ``traj_unsmoothed.txt``, of the stored ``traj_est.txt`` and
of ``traj_unsmoothed.txt`` smoothed by this checkout's smoother, with the smoother's report (spectral density,
frames down-weighted) and the sums over the runs.  Re-smoothing reads the 7-decimal centres of the file, so it can
differ from what a fresh run writes in the last digits, not in the ATE shown.

    .venv/bin/python benchmarks/bench_smoothing.py results/runs/bonn/*/dynamic results/ablate/*/runs/*
    .venv/bin/python benchmarks/bench_smoothing.py              # every run folder under results/
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
import tempfile
from pathlib import Path

from _bench import REPO  # sets up the path and the environment


def run_folders(patterns: list[str]) -> list[Path]:
    """Folders holding run.json and traj_unsmoothed.txt among ``patterns`` (folders or globs; default every run
    folder under results/), sorted, each once."""
    found = set()
    if not patterns:
        found = {p.parent for p in (REPO / "results").glob("**/traj_unsmoothed.txt")}
    for pat in patterns:
        matches = [Path(p) for p in sorted(glob.glob(pat))] if any(c in pat for c in "*?[") else [Path(pat)]
        found.update(m for m in matches if (m / "traj_unsmoothed.txt").is_file())
    return sorted(p for p in found if (p / "run.json").is_file())


def resmooth(run: Path) -> dict | None:
    """ATE cm of a run folder's unsmoothed, stored and re-smoothed trajectories and the smoother's report; None
    where its run.json names no ground truth file that exists."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from dynslam_cli.backend.smoothing import smooth_centres
    from dynslam_cli.eval.ate import compute_ate, read_tum
    from dynslam_cli.run.runner import write_tum

    gt = (json.loads((run / "run.json").read_text()).get("sequence") or {}).get("groundtruth")
    if not gt or not Path(gt).is_file():
        return None
    stamps, xyz, quat = read_tum(run / "traj_unsmoothed.txt", "trajectory")
    sm = smooth_centres(stamps, xyz)
    poses = np.tile(np.eye(4), (len(stamps), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(quat).as_matrix()  # the orientations as the run wrote them
    poses[:, :3, 3] = sm.centres
    with tempfile.TemporaryDirectory() as tmp:
        path = write_tum(Path(tmp) / "traj_est.txt", [f"{s:.6f}" for s in stamps], poses)  # as a run writes it
        new = compute_ate(path, gt).rmse_m * 100
    out = {"run": str(run), "unsmoothed": compute_ate(run / "traj_unsmoothed.txt", gt).rmse_m * 100,
           "stored": None, "resmoothed": new, "q": sm.q, "downweighted": sm.downweighted}
    if (run / "traj_est.txt").is_file():
        out["stored"] = compute_ate(run / "traj_est.txt", gt).rmse_m * 100
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="*", help="run folders or globs (default: every run folder under results/)")
    args = ap.parse_args(argv)
    rows = [r for r in (resmooth(p) for p in run_folders(args.runs)) if r is not None]
    if not rows:
        print("no run folder with traj_unsmoothed.txt and a ground truth found"
              + ("" if args.runs else " under results/ (give run folders as arguments)"))
        return 0
    print("| run | unsmoothed cm | stored traj_est cm | re-smoothed cm | q m²/s³ | frames down-weighted |")
    print("|---|---|---|---|---|---|")
    fmt = lambda v: "–" if v is None else f"{v:.2f}"  # noqa: E731
    for r in rows:
        print(f"| {r['run']} | {fmt(r['unsmoothed'])} | {fmt(r['stored'])} | {fmt(r['resmoothed'])} | {r['q']:.3g} | "
              f"{r['downweighted']} |")
    stored = [r["stored"] for r in rows if r["stored"] is not None]
    print(f"\n{len(rows)} runs: unsmoothed {sum(r['unsmoothed'] for r in rows):.2f} cm in all, re-smoothed "
          f"{sum(r['resmoothed'] for r in rows):.2f}" + (f", stored {sum(stored):.2f} ({len(stored)} runs)" if stored else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
