"""A Rerun recording of one or more run folders (``dynslam view``).

Each run goes under its own entity path prefix ``P`` (the run folder's name, with as many parent
folder names as it takes to tell the runs apart):

=============================  ==========================================================================
``P/trajectory/estimate``      LineStrips3D (static): the positions of traj_est.txt
``P/trajectory/groundtruth``   LineStrips3D (static): run.json ``sequence.groundtruth`` over the run's time
                               span, aligned to the estimate as ``dynslam eval-ate`` aligns them
                               (:func:`dynslam_cli.eval.ate.compute_ate` with the run's eval.align and
                               eval.max_time_diff; the inverse of its estimate-to-ground-truth transform)
``P/camera``                   Pinhole (static; the run's intrinsics) + Transform3D per frame (the estimate)
``P/camera/rgb``               the input colour image (JPEG), every N-th frame
``P/camera/depth``             the input depth (uint16, m × 5000), every N-th frame
``P/camera/mask``              the motion mask ``masks/<ts>.png`` (class 1 = dynamic), where saved
``P/camera/render_depth``      the map depth rendered for the check ``renders/<ts>_depth.png``, where saved
``P/mesh``                     Mesh3D (static): mesh.ply
``P/ate/error``                per-frame translation error (m) of the aligned estimate
``P/classifier/updates``       classifier updates so far, one point per line of classifier_updates.jsonl
=============================  ==========================================================================

Timelines: ``frame`` (position in traj_est.txt) and ``timestamp`` (the input timestamp, s).
Everything is drawn in the estimate's world frame, where the mesh is.  Input frames are read with
the data readers (association, undistortion and depth cut of the run's config.yaml) and matched to
the trajectory by timestamp.
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from dynslam_cli.errors import DynslamError
from dynslam_cli.eval import runs
from dynslam_cli.utils.io import atomic_path
from dynslam_cli.view import inputs
from dynslam_cli.view.inputs import DEPTH_UNITS, RunView

MAX_IMAGE_FRAMES = 100  # default --every: at most this many frames with images per run
JPEG_QUALITY = 85
FRUSTUM_M = 0.1  # distance of the drawn image plane from the camera centre (m)
INSTALL_HINT = 'pip install "dynslam_cli[view]"'


@dataclass
class ViewResult:
    out: Path
    size_bytes: int
    spawned: bool
    runs: list
    notes: list = field(default_factory=list)


def import_rerun():
    try:
        import rerun as rr
    except ImportError:
        raise DynslamError(f"dynslam view needs Rerun (rerun-sdk), which is not installed: {INSTALL_HINT}") from None
    return rr


# --------------------------------------------------------------------------------------------
# arguments
def default_out(run_dirs: Sequence[Path]) -> Path:
    """``RUN_DIR/recording.rrd`` for one run, else ``recording.rrd`` in the runs' common folder."""
    if len(run_dirs) == 1:
        return Path(run_dirs[0]) / "recording.rrd"
    return Path(os.path.commonpath([os.path.abspath(d) for d in run_dirs])) / "recording.rrd"


def run_prefixes(run_dirs: Sequence[Path], escape) -> list[str]:
    """Entity path prefixes: the shortest tails of the run folders' paths that differ."""
    parts = [Path(os.path.abspath(d)).parts[1:] or ("run",) for d in run_dirs]
    k = 1
    while k < max(len(p) for p in parts) and len({p[-k:] for p in parts}) < len(parts):
        k += 1
    return ["/".join(escape(x) for x in p[-k:]) for p in parts]


def _check_args(run_dirs: Sequence[Path], out: Path, every: Optional[int]) -> list[Path]:
    if not run_dirs:
        raise DynslamError("no run folder given")
    dirs = [runs.require_run_dir(d) for d in run_dirs]
    seen: dict = {}
    for d in dirs:
        key = d.resolve()
        if key in seen:
            raise DynslamError(f"run folder {d} given twice (also as {seen[key]})")
        seen[key] = d
        if not (d / "traj_est.txt").is_file():
            raise DynslamError(f"estimated trajectory traj_est.txt not found in run folder {d}")
    if every is not None and every < 1:
        raise DynslamError(f"--every must be >= 1, got {every}")
    if out.suffix != ".rrd":
        raise DynslamError(f"recording file {out} must end in .rrd")
    if out.is_dir():
        raise DynslamError(f"recording file {out} is a folder")
    return dirs


# --------------------------------------------------------------------------------------------
# reading one run
def _set_time(rec, frame: int, t: float) -> None:
    rec.set_time("frame", sequence=int(frame))
    rec.set_time("timestamp", timestamp=float(t))


def log_run(rr, rec, run_dir: Path, prefix: str, every: Optional[int]) -> RunView:
    """Log one run folder under ``prefix``; returns what was logged."""
    import cv2

    from dynslam_cli.data.tum import read_trajectory

    view = RunView(run_dir=run_dir, prefix=prefix)
    meta = runs.read_run_json(run_dir)
    est_file = run_dir / "traj_est.txt"
    t_est, T_est = read_trajectory(est_file)
    if len(t_est) == 0:
        raise DynslamError(f"estimated trajectory {est_file} holds no poses")
    n = len(t_est)
    view.frames = n
    view.every = every if every is not None else max(1, math.ceil(n / MAX_IMAGE_FRAMES))
    intr, width, height = runs.camera_model(run_dir, meta)
    P = prefix

    # trajectories
    rec.log(f"{P}/trajectory/estimate", rr.LineStrips3D([T_est[:, :3, 3]], colors=[[40, 120, 255]], radii=[0.004]),
            static=True)
    gt_xyz, ate = inputs.aligned_groundtruth(run_dir, meta, t_est, view)
    if gt_xyz is not None and len(gt_xyz):
        rec.log(f"{P}/trajectory/groundtruth", rr.LineStrips3D([gt_xyz], colors=[[40, 200, 80]], radii=[0.004]),
                static=True)
        view.groundtruth_poses, view.alignment, view.ate_rmse_m = len(gt_xyz), ate.alignment, ate.rmse_m
        for pos, f in inputs.frame_of(ate.timestamps, t_est).items():
            _set_time(rec, f, t_est[f])
            rec.log(f"{P}/ate/error", rr.Scalars(float(ate.errors[pos])))

    # camera: intrinsics once, the pose at every frame
    K = np.array([[intr[0], 0, intr[2]], [0, intr[1], intr[3]], [0, 0, 1]], dtype=np.float64)
    rec.log(f"{P}/camera", rr.Pinhole(image_from_camera=K, resolution=[width, height],
                                      camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=FRUSTUM_M), static=True)
    rec.log(f"{P}/camera/mask", rr.AnnotationContext([(0, "static", (0, 0, 0, 0)), (1, "dynamic", (255, 40, 40, 150))]),
            static=True)
    for i in range(n):
        _set_time(rec, i, t_est[i])
        rec.log(f"{P}/camera", rr.Transform3D(translation=T_est[i, :3, 3], mat3x3=T_est[i, :3, :3]))

    # images every N-th frame
    seq, to_seq = inputs.open_run_sequence(run_dir, meta, t_est, view)
    if seq is not None and (seq.intrinsics.width, seq.intrinsics.height) != (width, height):
        view.notes.append(f"input images are {seq.intrinsics.width}x{seq.intrinsics.height}, the run's camera "
                          f"{width}x{height}: images drawn at their own size")
    m_t, m_paths = inputs.stamped_files(run_dir / "masks", ".png")
    r_t, r_paths = inputs.stamped_files(run_dir / "renders", "_depth.png")
    mask_at = {f: m_paths[k] for k, f in inputs.frame_of(m_t, t_est).items()}
    render_at = {f: r_paths[k] for k, f in inputs.frame_of(r_t, t_est).items()}
    for i in range(0, n, view.every):
        _set_time(rec, i, t_est[i])
        j = to_seq.get(i)
        if j is not None:
            ok, jpg = cv2.imencode(".jpg", seq.load_rgb(j)[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            if not ok:
                raise DynslamError(f"cannot encode frame {j} of {seq.path} as JPEG")
            rec.log(f"{P}/camera/rgb", rr.EncodedImage(contents=jpg.tobytes(), media_type="image/jpeg"))
            depth = np.clip(np.round(seq.load_depth(j) * DEPTH_UNITS), 0, 65535).astype(np.uint16)
            rec.log(f"{P}/camera/depth", rr.DepthImage(depth, meter=DEPTH_UNITS))
            view.image_frames += 1
        if i in mask_at:
            mask = inputs.read_image(mask_at[i], "motion mask", (width, height))
            rec.log(f"{P}/camera/mask", rr.SegmentationImage((mask > 127).astype(np.uint8)))
            view.masks += 1
        if i in render_at:
            rendered = inputs.read_image(render_at[i], "rendered depth", (width, height), uint16=True)
            rec.log(f"{P}/camera/render_depth", rr.DepthImage(rendered, meter=DEPTH_UNITS))
            view.renders += 1

    # classifier updates: the count so far (and the loss after each update) over time
    upath = run_dir / "classifier_updates.jsonl"
    if upath.is_file():
        updates = inputs.read_updates(upath)
        placed = [(f, u) for f, u in zip(inputs.update_frames(updates, t_est), updates, strict=True) if f is not None]
        for count, (f, u) in enumerate(sorted(placed, key=lambda fu: fu[0]), 1):
            _set_time(rec, f, t_est[f])
            rec.log(f"{P}/classifier/updates", rr.Scalars(float(count)))
            if isinstance(u.get("loss_after"), (int, float)):
                rec.log(f"{P}/classifier/loss_after", rr.Scalars(float(u["loss_after"])))
        view.updates = len(placed)
        if len(placed) < len(updates):
            view.notes.append(f"{len(updates) - len(placed)} of {len(updates)} classifier updates match no frame")

    # the final mesh
    mpath = run_dir / "mesh.ply"
    if mpath.is_file():
        mesh = inputs.load_mesh(mpath)
        if len(mesh.faces) == 0:
            view.notes.append(f"mesh {mpath} has no faces")
        else:
            colors = mesh.visual.vertex_colors if mesh.visual.kind == "vertex" else None
            rec.log(f"{P}/mesh", rr.Mesh3D(vertex_positions=np.asarray(mesh.vertices, dtype=np.float32),
                                           triangle_indices=np.asarray(mesh.faces, dtype=np.uint32),
                                           vertex_normals=np.asarray(mesh.vertex_normals, dtype=np.float32),
                                           vertex_colors=colors), static=True)
            view.mesh_vertices = int(len(mesh.vertices))
    else:
        view.notes.append("no mesh.ply")
    return view


# --------------------------------------------------------------------------------------------
def _viewer_problem() -> str:
    """Why no viewer window can open here ('' when one may)."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return "no display (DISPLAY and WAYLAND_DISPLAY are unset)"
    return ""


def write_recording(run_dirs: Sequence[str | Path], out: Optional[str | Path] = None, every: Optional[int] = None,
                    spawn: bool = False) -> ViewResult:
    """Write one Rerun recording (``out``, default :func:`default_out`) of the run folders; with
    ``spawn`` also stream it to a Rerun viewer when one can be opened."""
    run_dirs = [Path(d) for d in run_dirs]
    out = Path(out) if out is not None else default_out(run_dirs) if run_dirs else Path("recording.rrd")
    dirs = _check_args(run_dirs, out, every)
    rr = import_rerun()
    notes: list[str] = []
    rec = rr.RecordingStream("dynslam")
    spawned = False
    if spawn:
        why = _viewer_problem()
        if not why:
            try:
                rr.spawn(connect=False)
                spawned = True
            except Exception as exc:  # no rerun executable, port taken, ...
                why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if not spawned:
            notes.append(f"viewer not opened: {why}")
    views = []
    with atomic_path(out) as tmp:
        try:
            rec.set_sinks(*([rr.FileSink(str(tmp))] + ([rr.GrpcSink()] if spawned else [])))
            for d, prefix in zip(dirs, run_prefixes(dirs, rr.escape_entity_path_part), strict=True):
                views.append(log_run(rr, rec, d, prefix, every))
            rec.flush()
        finally:
            rec.disconnect()
    return ViewResult(out=out, size_bytes=out.stat().st_size, spawned=spawned, runs=views, notes=notes)
