"""Absolute trajectory error (ATE) with evo's API.

The computation is exactly what ``evo_ape tum GT EST -a --t_max_diff D`` does: associate by
nearest timestamp (``evo.core.sync.associate_trajectories``, explicit max difference), align the
estimate to the ground truth (``PosePath3D.align`` = Umeyama, or ``align_origin``), and take APE on
the translation part (``evo.core.metrics.APE``).  The tests compare against the ``evo_ape``
console script and against the independent numpy Umeyama in :mod:`dynslam_cli.geometry.align`.

``rmse_still_m`` -- what a camera that never moves would score on the same matched ground truth:

* ``se3``, ``sim3``, ``none``: the best constant position under the alignment is the mean of the
  matched ground-truth positions (a constant trajectory is aligned by translating it; rotation and
  scale do nothing to a single point), so ``rmse_still = sqrt(mean_i ||p_i - mean(p)||^2)``;
  for ``none`` this is the lower bound over every constant position.
* ``origin``: origin alignment puts the still camera on the first matched ground-truth pose, so
  ``rmse_still = sqrt(mean_i ||p_i - p_0||^2)``.

An estimate whose ATE is not clearly below ``rmse_still_m`` tracked no better than standing still.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from dynslam_cli.errors import DynslamError
from dynslam_cli.eval import runs
from dynslam_cli.utils.io import write_json_atomic

ALIGN_MODES = ("se3", "sim3", "origin", "none")

STILL_DEFINITION = {
    "se3": "RMS distance of the matched GT positions to their mean (best constant position under SE(3) alignment)",
    "sim3": "RMS distance of the matched GT positions to their mean (best constant position under Sim(3) alignment)",
    "none": "RMS distance of the matched GT positions to their mean (best constant position, no alignment)",
    "origin": "RMS distance of the matched GT positions to the first matched GT position (still camera aligned at the origin)",
}


@dataclass
class AteResult:
    rmse_m: float
    mean_m: float
    median_m: float
    min_m: float
    max_m: float
    std_m: float
    rmse_still_m: float
    rmse_still_definition: str
    matched: int
    est_poses: int
    gt_poses: int
    alignment: str
    max_diff_s: float
    gt_file: str
    est_file: str
    rotation: list = field(default_factory=list)
    translation: list = field(default_factory=list)
    scale: float = 1.0
    # per matched pose (not written to ate.json)
    timestamps: Optional[np.ndarray] = field(default=None, repr=False)
    errors: Optional[np.ndarray] = field(default=None, repr=False)
    est_xyz: Optional[np.ndarray] = field(default=None, repr=False)
    gt_xyz: Optional[np.ndarray] = field(default=None, repr=False)

    def to_json(self) -> dict:
        d = asdict(self)
        for k in ("timestamps", "errors", "est_xyz", "gt_xyz"):
            d.pop(k)
        return d


def read_tum(path: str | Path, what: str = "trajectory") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(stamps N, xyz N×3, quat_xyzw N×4)`` of a TUM file, validated line by line."""
    path = Path(path)
    if not path.is_file():
        raise DynslamError(f"{what} file not found: {path}")
    rows = []
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise DynslamError(f"corrupt {what} file {path}: not text") from None
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise DynslamError(f"corrupt {what} file {path} line {lineno}: expected 8 values "
                               f"'timestamp tx ty tz qx qy qz qw', got {len(parts)}")
        try:
            vals = [float(v) for v in parts]
        except ValueError:
            raise DynslamError(f"corrupt {what} file {path} line {lineno}: not a number in '{s[:60]}'") from None
        if not np.isfinite(vals).all():
            raise DynslamError(f"{what} file {path} line {lineno}: NaN or infinite value")
        if np.linalg.norm(vals[4:]) < 1e-9:
            raise DynslamError(f"{what} file {path} line {lineno}: zero quaternion")
        rows.append(vals)
    if not rows:
        raise DynslamError(f"{what} file {path} holds no poses")
    mat = np.asarray(rows, dtype=np.float64)
    return mat[:, 0], mat[:, 1:4], mat[:, 4:8]


def _evo_traj(path: Path, what: str):
    from evo.core.trajectory import PoseTrajectory3D

    stamps, xyz, quat_xyzw = read_tum(path, what)
    # same construction as evo.tools.file_interface.read_tum_trajectory_file
    return PoseTrajectory3D(xyz, np.roll(quat_xyzw, 1, axis=1), stamps, name=path.name)


def compute_ate(est_file: str | Path, gt_file: str | Path, align: str = "se3",
                max_diff: float = 0.02) -> AteResult:
    """ATE of the estimate ``est_file`` against ``gt_file`` (both TUM, camera-to-world)."""
    if align not in ALIGN_MODES:
        raise DynslamError(f"unknown alignment '{align}'; choose one of {', '.join(ALIGN_MODES)}")
    if not (max_diff > 0 and np.isfinite(max_diff)):
        raise DynslamError(f"max time difference must be a positive number, got {max_diff}")
    import logging

    from evo.core import metrics, sync

    logging.getLogger("evo").setLevel(logging.ERROR)
    est_file, gt_file = Path(est_file), Path(gt_file)
    gt = _evo_traj(gt_file, "ground-truth")
    est = _evo_traj(est_file, "estimated trajectory")
    n_est, n_gt = est.num_poses, gt.num_poses
    try:
        gt_m, est_m = sync.associate_trajectories(gt, est, max_diff=max_diff)
    except sync.SyncException:
        raise DynslamError(f"no timestamps of {est_file} associate with {gt_file} within {max_diff} s "
                           "(wrong ground truth, or raise --max-diff)") from None
    n = est_m.num_poses
    if align in ("se3", "sim3") and n < 3:
        raise DynslamError(f"only {n} poses of {est_file} associate with {gt_file} within {max_diff} s; "
                           f"{align} alignment needs at least 3")
    rot, trans, scale = np.eye(3), np.zeros(3), 1.0
    if align in ("se3", "sim3"):
        from evo.core.geometry import GeometryException

        try:
            rot, trans, scale = est_m.align(gt_m, correct_scale=(align == "sim3"))
        except GeometryException:
            raise DynslamError(f"cannot {align}-align {est_file} to {gt_file}: the matched positions are degenerate "
                               "(all on one point or line); use --align origin or none") from None
    elif align == "origin":
        t = est_m.align_origin(gt_m)
        rot, trans = t[:3, :3], t[:3, 3]
    if not np.isfinite(est_m.positions_xyz).all():
        raise DynslamError(f"alignment of {est_file} to {gt_file} produced non-finite poses (degenerate trajectory)")
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((gt_m, est_m))
    st = ape.get_all_statistics()
    gt_xyz = gt_m.positions_xyz
    centre = gt_xyz[0] if align == "origin" else gt_xyz.mean(axis=0)
    still = float(np.sqrt(np.mean(np.sum((gt_xyz - centre) ** 2, axis=1))))
    return AteResult(
        rmse_m=float(st["rmse"]), mean_m=float(st["mean"]), median_m=float(st["median"]),
        min_m=float(st["min"]), max_m=float(st["max"]), std_m=float(st["std"]),
        rmse_still_m=still, rmse_still_definition=STILL_DEFINITION[align],
        matched=int(n), est_poses=int(n_est), gt_poses=int(n_gt), alignment=align,
        max_diff_s=float(max_diff), gt_file=str(gt_file), est_file=str(est_file),
        rotation=np.asarray(rot).tolist(), translation=np.asarray(trans).tolist(), scale=float(scale),
        timestamps=np.asarray(est_m.timestamps), errors=np.asarray(ape.error),
        est_xyz=np.asarray(est_m.positions_xyz), gt_xyz=np.asarray(gt_xyz),
    )


def evaluate_run_ate(run_dir: str | Path, gt: Optional[str | Path] = None, align: Optional[str] = None,
                     max_diff: Optional[float] = None, plot: bool = True,
                     include_incomplete: bool = False, online: bool = False) -> AteResult:
    """ATE of a run folder: reads traj_est.txt, writes ate.json (and ate.png); ``online``: reads
    traj_online.txt (each frame's pose when it was done), writes ate_online.json (and ate_online.png).

    A run whose run.json is not completed is an error unless ``include_incomplete``.
    """
    run_dir = runs.require_completed(run_dir, include_incomplete)
    cfg = runs.eval_config_for(run_dir)
    name, out = ("traj_online.txt", "ate_online") if online else ("traj_est.txt", "ate")
    est_file = run_dir / name
    if not est_file.is_file():
        raise DynslamError(f"estimated trajectory {name} not found in run folder {run_dir}")
    if gt is None:
        gt = runs.groundtruth_path(run_dir)
        if gt is None:
            raise DynslamError(f"no ground truth for run {run_dir}: run.json has no sequence.groundtruth; pass --gt FILE")
    res = compute_ate(est_file, gt, align or cfg.align, max_diff if max_diff is not None else cfg.max_time_diff)
    write_json_atomic(run_dir / f"{out}.json", res.to_json())
    if plot:
        from dynslam_cli.eval.plots import plot_ate

        plot_ate(res, run_dir / f"{out}.png", run_dir=run_dir)
    return res
