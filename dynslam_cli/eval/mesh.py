"""Mesh accuracy / completion against a reference surface.

* Accuracy: mean distance from points sampled on the estimated mesh to the reference.
* Completion: mean distance from points sampled on the reference to the estimated mesh.
* Completion ratio: fraction of reference points closer than ``eval.completion_threshold``
  (5 cm) to the estimate.

``MESH_SAMPLES`` (200k) points are drawn on each surface with a fixed seed (trimesh's
area-weighted ``sample_surface`` for meshes; a point-cloud reference is used as it is, or
randomly subsampled when it holds more points).  Distances are nearest neighbours in a scipy
``cKDTree`` between the two samples.

Frames.  The estimated mesh is in the run's world frame (the frame of traj_est.txt).  The
reference is brought into that frame by anchoring the first estimated camera:
``T_ref->est = T_est(t0) · C0^-1`` where ``C0`` is the pose of the first camera in the reference
frame: the ground-truth pose at ``t0`` for synthetic scenes (their ground truth is the camera in
the world of ``static_mesh.ply``), and for Bonn the dataset's own composition
``C0 = T_ros · T_gt(t0) · T_ros · T_m`` (``T_m``'s 3×3 block projected onto SO(3)).  When the run
starts at the ground-truth pose this is the identity.

Culling (``--cull``, default on).  Parts of the reference the camera never saw cannot be
completed, so for *completion* the reference is first reduced to the points inside at least one
estimated camera frustum: projected inside the image, in front of the camera and no farther
than ``CULL_MAX_DEPTH`` (5 m); up to ``CULL_VIEWS`` (200) poses evenly spread over the trajectory
are used.  There is no occlusion test (a point behind a wall inside the frustum is kept), so
culling is conservative.  Accuracy is always measured against the whole reference (culling must
not make a correct estimated surface look wrong).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from dynslam_cli.errors import DynslamError
from dynslam_cli.eval import runs
from dynslam_cli.utils.io import write_json_atomic

# Points sampled on each mesh for accuracy/completion, with this seed (results are repeatable); camera poses (evenly
# spread) whose frusta, this deep (m), cull the reference for completion.
MESH_SAMPLES = 200000
SEED = 0
CULL_VIEWS = 200
CULL_MAX_DEPTH = 5.0

T_ROS = np.array([[-1, 0, 0, 0], [0, 0, 1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
T_M = np.array([[1.0157, 0.1828, -0.2389, 0.0113], [0.0009, -0.8431, -0.6413, -0.0098],
                [-0.3009, 0.6147, -0.8085, 0.0111], [0, 0, 0, 1]], dtype=np.float64)


@dataclass
class MeshResult:
    accuracy_m: float
    completion_m: float
    completion_ratio: float
    threshold_m: float
    samples: int
    est_points: int
    ref_points: int
    ref_points_after_cull: int
    culled: bool
    est_file: str
    ref_file: str
    ref_to_est: list
    seed: int

    def to_json(self) -> dict:
        d = asdict(self)
        d["accuracy_cm"] = 100 * self.accuracy_m
        d["completion_cm"] = 100 * self.completion_m
        return d


def project_to_so3(m: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def bonn_camera_in_reference(t_gt: np.ndarray) -> np.ndarray:
    """Pose of the camera in Bonn's reference-cloud frame: ``T_ros · T_gt · T_ros · T_m``.

    Uses the data layer's :func:`dynslam_cli.data.bonn.gt_to_reference` (T_m made rigid) when
    present; the same math inline otherwise.
    """
    try:
        from dynslam_cli.data.bonn import gt_to_reference
    except ImportError:
        gt_to_reference = None
    if gt_to_reference is not None:
        return gt_to_reference(np.asarray(t_gt, dtype=np.float64))
    tm = T_M.copy()
    tm[:3, :3] = project_to_so3(T_M[:3, :3])
    return T_ROS @ np.asarray(t_gt, dtype=np.float64) @ T_ROS @ tm


def pose_matrix(xyz: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    t = np.eye(4)
    t[:3, :3] = Rotation.from_quat(np.asarray(quat_xyzw, dtype=np.float64)).as_matrix()
    t[:3, 3] = xyz
    return t


def load_points_or_mesh(path: str | Path, what: str):
    """A trimesh.Trimesh (faces present) or an N×3 array (point cloud)."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise DynslamError(f"{what} not found: {path}")
    try:
        geom = trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises many types on bad files
        raise DynslamError(f"cannot read {what} {path}: {exc}") from None
    if isinstance(geom, trimesh.Scene):
        geoms = list(geom.geometry.values())
        if not geoms:
            raise DynslamError(f"{what} {path} is empty")
        geom = trimesh.util.concatenate(geoms) if all(isinstance(g, trimesh.Trimesh) for g in geoms) else geoms[0]
    if isinstance(geom, trimesh.Trimesh) and len(geom.faces) > 0:
        if not np.isfinite(geom.vertices).all():
            raise DynslamError(f"{what} {path} has NaN or infinite vertices")
        return geom
    pts = np.asarray(getattr(geom, "vertices", np.empty((0, 3))), dtype=np.float64)
    if len(pts) == 0:
        raise DynslamError(f"{what} {path} holds no points or faces")
    if not np.isfinite(pts).all():
        raise DynslamError(f"{what} {path} has NaN or infinite points")
    return pts


def sample_points(geom, n: int, seed: int) -> np.ndarray:
    import trimesh

    if isinstance(geom, trimesh.Trimesh):
        pts, _ = trimesh.sample.sample_surface(geom, n, seed=seed)
        return np.asarray(pts, dtype=np.float64)
    pts = np.asarray(geom, dtype=np.float64)
    if len(pts) > n:
        idx = np.random.default_rng(seed).choice(len(pts), n, replace=False)
        pts = pts[idx]
    return pts


def frustum_mask(points: np.ndarray, poses_c2w: list[np.ndarray], intrinsics: list[float], width: int,
                 height: int, max_depth: float, near: float = 0.05) -> np.ndarray:
    """True for points inside at least one camera frustum (no occlusion test)."""
    fx, fy, cx, cy = intrinsics
    keep = np.zeros(len(points), dtype=bool)
    for c2w in poses_c2w:
        w2c = np.linalg.inv(c2w)
        pc = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = fx * pc[:, 0] / z + cx
            v = fy * pc[:, 1] / z + cy
        keep |= (z > near) & (z <= max_depth) & (u >= -0.5) & (u < width - 0.5) & (v >= -0.5) & (v < height - 0.5)
    return keep


def mesh_metrics(est_pts: np.ndarray, ref_pts_all: np.ndarray, ref_pts_completion: np.ndarray,
                 threshold: float) -> tuple[float, float, float]:
    from scipy.spatial import cKDTree

    if len(est_pts) == 0 or len(ref_pts_all) == 0 or len(ref_pts_completion) == 0:
        raise DynslamError("mesh metrics need non-empty estimated and reference point sets "
                           "(is the reference outside every camera frustum? try --no-cull)")
    d_acc, _ = cKDTree(ref_pts_all).query(est_pts, k=1, workers=1)
    d_comp, _ = cKDTree(est_pts).query(ref_pts_completion, k=1, workers=1)
    return float(np.mean(d_acc)), float(np.mean(d_comp)), float(np.mean(d_comp < threshold))


def compute_mesh_metrics(est_file: str | Path, ref_file: str | Path, ref_to_est: Optional[np.ndarray] = None,
                         samples: int = 200000, threshold: float = 0.05, seed: int = 0,
                         cull_poses: Optional[list] = None, intrinsics: Optional[list] = None,
                         width: int = 640, height: int = 480, cull_max_depth: float = 5.0) -> MeshResult:
    """Metrics of mesh ``est_file`` against ``ref_file`` (mesh or cloud), reference moved by ``ref_to_est``."""
    est = load_points_or_mesh(est_file, "estimated mesh")
    ref = load_points_or_mesh(ref_file, "reference")
    t = np.eye(4) if ref_to_est is None else np.asarray(ref_to_est, dtype=np.float64)
    if not np.isfinite(t).all():
        raise DynslamError(f"reference transform for {ref_file} is not finite")
    est_pts = sample_points(est, samples, seed)
    import trimesh

    if isinstance(ref, trimesh.Trimesh):
        ref = ref.copy()
        ref.apply_transform(t)
    else:
        ref = ref @ t[:3, :3].T + t[:3, 3]
    ref_all = sample_points(ref, samples, seed + 1)
    ref_comp, culled = ref_all, False
    if cull_poses is not None:
        if intrinsics is None:
            raise DynslamError("culling needs the camera intrinsics")
        if isinstance(ref, trimesh.Trimesh):
            # cull faces (centroids), then sample the kept part: the full sample count on what was seen
            keep = frustum_mask(ref.triangles_center, cull_poses, intrinsics, width, height, cull_max_depth)
            if keep.any():
                sub = ref.submesh([np.flatnonzero(keep)], append=True)
                ref_comp = sample_points(sub, samples, seed + 2)
            else:
                ref_comp = np.empty((0, 3))
        else:
            keep = frustum_mask(ref, cull_poses, intrinsics, width, height, cull_max_depth)
            ref_comp = sample_points(ref[keep], samples, seed + 2)
        culled = True
    acc, comp, ratio = mesh_metrics(est_pts, ref_all, ref_comp, threshold)
    return MeshResult(accuracy_m=acc, completion_m=comp, completion_ratio=ratio, threshold_m=float(threshold),
                      samples=int(samples), est_points=len(est_pts), ref_points=len(ref_all),
                      ref_points_after_cull=len(ref_comp), culled=culled, est_file=str(est_file),
                      ref_file=str(ref_file), ref_to_est=t.tolist(), seed=int(seed))


def _first_poses(run_dir: Path, gt_file: Optional[Path], max_diff: float):
    """(T_est(t0), T_gt(t0) or None, all estimated poses)."""
    from dynslam_cli.eval.ate import read_tum

    stamps, xyz, quat = read_tum(run_dir / "traj_est.txt", "estimated trajectory")
    poses = [pose_matrix(p, q) for p, q in zip(xyz, quat, strict=False)]
    t_gt0 = None
    if gt_file is not None:
        g_st, g_xyz, g_q = read_tum(gt_file, "ground-truth")
        i = int(np.argmin(np.abs(g_st - stamps[0])))
        if abs(g_st[i] - stamps[0]) > max_diff:
            raise DynslamError(f"first estimated timestamp {stamps[0]:.6f} of {run_dir} has no ground-truth pose "
                               f"within {max_diff} s in {gt_file}")
        t_gt0 = pose_matrix(g_xyz[i], g_q[i])
    return poses[0], t_gt0, poses


def evaluate_run_mesh(run_dir: str | Path, ref: Optional[str | Path] = None, cull: bool = True,
                      gt: Optional[str | Path] = None, include_incomplete: bool = False) -> MeshResult:
    """Mesh metrics of a run folder's mesh.ply; writes mesh_metrics.json.

    A run whose run.json is not completed is an error unless ``include_incomplete``.
    """
    run_dir = runs.require_completed(run_dir, include_incomplete)
    meta = runs.read_run_json(run_dir)
    cfg = runs.eval_config_for(run_dir)
    est_file = run_dir / "mesh.ply"
    if not est_file.is_file():
        raise DynslamError(f"mesh.ply not found in run folder {run_dir}")
    dataset = runs.dataset_of(run_dir, meta)
    gt_file = Path(gt) if gt else runs.groundtruth_path(run_dir, meta)
    if ref is None:
        sp = runs.sequence_path(run_dir, meta)
        if dataset == "synth" and sp is not None:
            ref = sp / "static_mesh.ply"
        else:
            raise DynslamError(f"no reference surface for run {run_dir} ({dataset or 'unknown dataset'}): "
                               "pass --ref FILE (Bonn: the laser-scanned reference cloud)")
    need_anchor = dataset in ("synth", "bonn")
    t_est0, t_gt0, poses = _first_poses(run_dir, gt_file if need_anchor else None, cfg.max_time_diff)
    if not need_anchor:
        ref_to_est = np.eye(4)  # a reference given for another dataset is taken to be in the run's frame
    else:
        if t_gt0 is None:
            raise DynslamError(f"run {run_dir} has no ground truth to place the reference; pass --gt FILE")
        c0 = bonn_camera_in_reference(t_gt0) if dataset == "bonn" else t_gt0
        ref_to_est = t_est0 @ np.linalg.inv(c0)
    cull_poses = intr = None
    width, height = 640, 480
    if cull:
        intr, width, height = runs.camera_model(run_dir, meta)
        step = max(1, int(np.ceil(len(poses) / CULL_VIEWS)))
        cull_poses = poses[::step]
    res = compute_mesh_metrics(est_file, ref, ref_to_est, samples=MESH_SAMPLES,
                               threshold=cfg.completion_threshold, seed=SEED, cull_poses=cull_poses,
                               intrinsics=intr, width=width, height=height, cull_max_depth=CULL_MAX_DEPTH)
    write_json_atomic(run_dir / "mesh_metrics.json", res.to_json())
    return res
