"""What ``dynslam view`` reads from a run folder: the input frames matched to the trajectory by
timestamp, the aligned ground truth, masks / renders / classifier updates, the mesh.  Whatever cannot
be shown is noted in the run's :class:`RunView`."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from dynslam_cli.errors import DynslamError
from dynslam_cli.eval import runs

DEPTH_UNITS = 5000.0  # uint16 depth units per metre (input depth re-quantised; renders/ as written)
MATCH_S = 1e-3  # max timestamp difference (s) between the trajectory and masks/renders/updates


@dataclass
class RunView:
    """What one run contributed to the recording."""

    run_dir: Path
    prefix: str
    frames: int = 0  # trajectory poses (frusta) on the timeline
    every: int = 1
    image_frames: int = 0  # frames with rgb/depth logged
    groundtruth_poses: int = 0
    alignment: str = ""
    ate_rmse_m: Optional[float] = None
    masks: int = 0
    renders: int = 0
    updates: int = 0
    mesh_vertices: int = 0
    notes: list = field(default_factory=list)  # what could not be shown, and why


def frame_of(stamps, t_est: np.ndarray) -> dict:
    """``{position in stamps: trajectory frame}`` for stamps within MATCH_S of a trajectory time."""
    from dynslam_cli.data.tum import associate

    return dict(associate(np.asarray(stamps, dtype=np.float64), t_est, MATCH_S))


def stamped_files(folder: Path, suffix: str) -> tuple[list[float], list[Path]]:
    """``(timestamps, paths)`` of ``folder/<ts><suffix>`` files whose ``<ts>`` is a number."""
    stamps, paths = [], []
    if folder.is_dir():
        for p in sorted(folder.glob(f"*{suffix}")):
            try:
                stamps.append(float(p.name[: -len(suffix)]))
            except ValueError:
                continue
            paths.append(p)
    return stamps, paths


def read_image(path: Path, what: str, size: tuple[int, int], uint16: bool = False) -> np.ndarray:
    """A single-channel PNG at the camera size ``(w, h)`` (nearest-neighbour resize when smaller)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED if uint16 else cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise DynslamError(f"corrupt {what} {path}: not a readable image")
    if uint16 and (img.dtype != np.uint16 or img.ndim != 2):
        raise DynslamError(f"{what} {path} must be single-channel uint16 (m × {DEPTH_UNITS:g}), got {img.dtype} "
                           f"with {1 if img.ndim == 2 else img.shape[2]} channels")
    if (img.shape[1], img.shape[0]) != size:
        img = cv2.resize(img, size, interpolation=cv2.INTER_NEAREST)
    return img


def data_config(run_dir: Path, meta: dict, view: RunView):
    """The run's config (config.yaml) for reading its sequence; the dataset's when it has none."""
    from dynslam_cli.config import config_from_file, load_config

    cpath = run_dir / "config.yaml"
    if cpath.is_file():
        try:
            return config_from_file(cpath)
        except DynslamError as exc:
            view.notes.append(f"config.yaml not usable ({exc}); input frames read with the dataset's settings")
    ds = runs.dataset_of(run_dir, meta)
    name = str(runs.sequence_info(run_dir, meta).get("name") or "") or None
    return load_config(ds if ds in ("tum", "bonn", "synth") else None, name)


def open_run_sequence(run_dir: Path, meta: dict, t_est: np.ndarray, view: RunView):
    """The run's input sequence (all frames) and ``{trajectory frame: sequence index}``."""
    from dynslam_cli.data.tum import read_folder

    sp = runs.sequence_path(run_dir, meta)
    if sp is None or not sp.is_dir():
        view.notes.append("input images not shown: " + ("run.json has no sequence.path" if sp is None
                                                        else f"sequence folder {sp} not found"))
        return None, {}
    cfg = data_config(run_dir, meta, view)
    cfg.data.start, cfg.data.frames, cfg.data.stride = 0, 0, 1
    info = runs.sequence_info(run_dir, meta)
    seq = read_folder(sp, cfg, dataset=runs.dataset_of(run_dir, meta), name=str(info.get("name") or sp.name),
                      spec=str(sp))
    to_seq = {f: j for j, f in frame_of(seq.timestamps, t_est).items()}
    if not to_seq:
        view.notes.append(f"input images not shown: no frame of {sp} has a timestamp of traj_est.txt")
    return seq, to_seq


def aligned_groundtruth(run_dir: Path, meta: dict, t_est: np.ndarray, view: RunView):
    """Ground-truth positions over the run's time span in the estimate's frame, and the ATE result."""
    from dynslam_cli.eval.ate import compute_ate, read_tum

    gt_file = runs.groundtruth_path(run_dir, meta)
    if gt_file is None:
        view.notes.append("ground truth not shown: run.json has no sequence.groundtruth")
        return None, None
    cfg = runs.eval_config_for(run_dir)
    try:
        res = compute_ate(run_dir / "traj_est.txt", gt_file, cfg.align, cfg.max_time_diff)
        gt_t, gt_xyz, _ = read_tum(gt_file, "ground-truth")
    except DynslamError as exc:
        view.notes.append(f"ground truth not shown: {exc}")
        return None, None
    rot, trans = np.asarray(res.rotation, dtype=np.float64), np.asarray(res.translation, dtype=np.float64)
    keep = (gt_t >= t_est[0] - cfg.max_time_diff) & (gt_t <= t_est[-1] + cfg.max_time_diff)
    # compute_ate maps the estimate onto the ground truth: g = s R e + t, so e = R^T (g - t) / s
    return (gt_xyz[keep] - trans) @ rot / res.scale, res


def read_updates(path: Path) -> list[dict]:
    out = []
    for no, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            d = json.loads(line)
        except json.JSONDecodeError:
            d = None
        if not isinstance(d, dict):
            raise DynslamError(f"corrupt classifier_updates.jsonl {path} line {no}: expected a JSON object")
        out.append(d)
    return out


def update_frames(updates: list[dict], t_est: np.ndarray) -> list[Optional[int]]:
    """The trajectory frame of each update: by its ``timestamp``, else its ``frame`` index."""
    stamps, which = [], []
    for k, u in enumerate(updates):
        try:
            stamps.append(float(u.get("timestamp")))
            which.append(k)
        except (TypeError, ValueError):
            continue
    frames: list[Optional[int]] = [None] * len(updates)
    for pos, f in frame_of(stamps, t_est).items():
        frames[which[pos]] = f
    for k, u in enumerate(updates):
        f = u.get("frame")
        if frames[k] is None and isinstance(f, int) and 0 <= f < len(t_est):
            frames[k] = f
    return frames


def load_mesh(path: Path):
    import trimesh

    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many kinds on a bad file
        raise DynslamError(f"corrupt mesh {path}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    return mesh


# --------------------------------------------------------------------------------------------
# logging one run
