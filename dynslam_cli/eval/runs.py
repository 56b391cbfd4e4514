"""Reading a run folder (see DEVELOPING.md, "Run folder") for evaluation.

Only result files are read here: ``run.json``, ``config.yaml``, ``traj_est.txt`` and the files
the evaluators wrote.  Every problem is a one-line :class:`DynslamError` naming the file.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Optional

import numpy as np

from dynslam_cli.errors import DynslamError

# Intrinsics [fx, fy, cx, cy] of the datasets when a run's config does not record them.
DATASET_INTRINSICS = {
    "bonn": [542.822841, 542.576870, 315.593520, 237.756098],
    "fr1": [517.3, 516.5, 318.6, 255.3],
    "fr2": [520.9, 521.0, 325.1, 249.7],
    "fr3": [535.4, 539.2, 320.1, 247.6],
}


def require_run_dir(run_dir: str | Path) -> Path:
    p = Path(run_dir)
    if not p.is_dir():
        raise DynslamError(f"run folder not found: {p}")
    return p


def read_json(path: Path, what: str = "JSON file") -> Any:
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise DynslamError(f"{what} not found: {path}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DynslamError(f"corrupt {what} {path}: {exc}") from None


def read_run_json(run_dir: Path, required: bool = False) -> dict:
    """``run.json`` of a run folder as a dict ({} when absent and not ``required``)."""
    path = Path(run_dir) / "run.json"
    if not path.is_file():
        if required:
            raise DynslamError(f"run.json not found in run folder {run_dir}")
        return {}
    data = read_json(path, "run.json")
    if not isinstance(data, dict):
        raise DynslamError(f"corrupt run.json {path}: expected a JSON object")
    return data


def read_run_config(run_dir: Path) -> dict:
    """The run's resolved ``config.yaml`` as a plain dict ({} when absent)."""
    import yaml

    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        return {}
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise DynslamError(f"corrupt config.yaml {path}: {getattr(exc, 'problem', exc)}") from None
    return data if isinstance(data, dict) else {}


def eval_config_for(run_dir: Optional[Path]):
    """EvalConfig defaults overlaid with the ``eval`` section of the run's config.yaml."""
    import dynslam_cli.config  # noqa: F401 - import the config package first (avoids a circular import)
    from dynslam_cli.eval.config import EvalConfig

    cfg = EvalConfig()
    section = read_run_config(run_dir).get("eval", {}) if run_dir is not None else {}
    if isinstance(section, dict):
        names = {f.name for f in dataclasses.fields(EvalConfig)}
        for key, value in section.items():
            if key in names and value is not None:
                setattr(cfg, key, type(getattr(cfg, key))(value))
    return cfg


def _resolve(path_text: str, run_dir: Path) -> Path:
    p = Path(path_text).expanduser()
    if p.is_absolute():
        return p
    for base in (Path.cwd(), run_dir):
        if (base / p).exists():
            return base / p
    return p


def sequence_info(run_dir: Path, meta: Optional[dict] = None) -> dict:
    meta = read_run_json(run_dir) if meta is None else meta
    seq = meta.get("sequence") or {}
    return seq if isinstance(seq, dict) else {}


def groundtruth_path(run_dir: Path, meta: Optional[dict] = None) -> Optional[Path]:
    """The ground-truth file recorded in run.json (sequence.groundtruth), else the sequence's."""
    seq = sequence_info(run_dir, meta)
    if seq.get("groundtruth"):
        return _resolve(str(seq["groundtruth"]), run_dir)
    if seq.get("path") and (_resolve(str(seq["path"]), run_dir) / "groundtruth.txt").is_file():
        return _resolve(str(seq["path"]), run_dir) / "groundtruth.txt"
    return None


def sequence_path(run_dir: Path, meta: Optional[dict] = None) -> Optional[Path]:
    seq = sequence_info(run_dir, meta)
    return _resolve(str(seq["path"]), run_dir) if seq.get("path") else None


def dataset_of(run_dir: Path, meta: Optional[dict] = None) -> str:
    seq = sequence_info(run_dir, meta)
    if seq.get("dataset"):
        return str(seq["dataset"])
    sp = sequence_path(run_dir, meta)
    if sp is not None and (sp / "synth.json").is_file():
        return "synth"
    return ""


def camera_model(run_dir: Path, meta: Optional[dict] = None) -> tuple[list[float], int, int]:
    """``([fx, fy, cx, cy], width, height)`` of the run's camera.

    Looked up, in order: run.json ``sequence.intrinsics`` (and ``width``/``height``), the run's
    config.yaml ``data.intrinsics``, the scene's ``synth.json`` (synthetic runs), the dataset's
    published values (Bonn, TUM fr1/fr2/fr3).  The image size defaults to 640×480.
    """
    meta = read_run_json(run_dir) if meta is None else meta
    seq = sequence_info(run_dir, meta)
    width = int(seq.get("width") or 640)
    height = int(seq.get("height") or 480)
    intr = seq.get("intrinsics")
    if not intr:
        intr = (read_run_config(run_dir).get("data") or {}).get("intrinsics")
    sp = sequence_path(run_dir, meta)
    if sp is not None and (sp / "synth.json").is_file():
        sj = read_json(sp / "synth.json", "synth.json")
        if not intr:
            intr = sj.get("intrinsics")
        size = sj.get("size")
        if isinstance(size, (list, tuple)) and len(size) == 2:
            width, height = int(size[0]), int(size[1])
        width = int(sj.get("width", width))
        height = int(sj.get("height", height))
    if not intr:
        ds = dataset_of(run_dir, meta)
        name = str(seq.get("name", ""))
        key = "bonn" if ds == "bonn" else name[:3] if ds == "tum" else ""
        intr = DATASET_INTRINSICS.get(key)
    if not intr or len(intr) != 4:
        raise DynslamError(f"camera intrinsics of run {run_dir} unknown: not in run.json, config.yaml "
                           "data.intrinsics, synth.json or the dataset table")
    return [float(v) for v in intr], width, height


def incomplete_reason(run_dir: Path, include_incomplete: bool = False) -> Optional[str]:
    """None when the run counts as complete, else one line saying why it does not.

    The one completeness check of every evaluator (eval-ate, eval-mesh, eval-masks, tables,
    ablate): a run is complete when its ``run.json`` says ``"status": "completed"``.  A running,
    failed or interrupted run, one without run.json and one whose run.json cannot be read are
    incomplete; with ``include_incomplete`` only a missing folder is.  The caller decides whether
    the line is an error (a run folder given on its own) or a warning (one folder of many).
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        return f"run folder not found: {run_dir}"
    if include_incomplete:
        return None
    try:
        meta = read_run_json(run_dir)
    except DynslamError:
        why = "run.json is corrupt"
    else:
        status = meta.get("status")
        if status == "completed":
            return None
        why = ("no run.json" if not (run_dir / "run.json").is_file()
               else f"run.json status: {status if isinstance(status, str) else repr(status)}")
    return f"run {run_dir} is not completed ({why}); pass --include-incomplete to use it anyway"


def require_completed(run_dir: str | Path, include_incomplete: bool = False) -> Path:
    """The run folder as a Path; DynslamError (see :func:`incomplete_reason`) unless it is complete."""
    reason = incomplete_reason(Path(run_dir), include_incomplete)
    if reason is not None:
        raise DynslamError(reason)
    return Path(run_dir)


def select_completed(run_dirs, include_incomplete: bool = False) -> tuple[list[Path], list[str]]:
    """``(complete run folders, one warning line per skipped folder)``; a missing folder is an error."""
    keep, warnings = [], []
    for d in run_dirs:
        d = require_run_dir(d)
        reason = incomplete_reason(d, include_incomplete)
        if reason is None:
            keep.append(d)
        else:
            warnings.append(f"skipped: {reason}")
    return keep, warnings


def is_finished(run_dir: Path) -> bool:
    """A completed run (see :func:`incomplete_reason`) whose ate.json exists."""
    return incomplete_reason(run_dir) is None and (Path(run_dir) / "ate.json").is_file()


def is_number(v: Any) -> bool:
    """A JSON number (int or float, not a bool); NaN and inf count (the tables drop them)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def read_result_json(path: Path, numbers: tuple = (), number_maps: tuple = ()) -> tuple[dict, Optional[str]]:
    """``(data, problem)`` of a result file (ate.json, mesh_metrics.json, timing.json, ...).

    ``({}, None)`` when the file is absent.  ``({}, one line naming the file)`` when it is not
    readable JSON, not an object, a key of ``numbers`` holds something other than a number or
    null, or a key of ``number_maps`` something other than an object of numbers: the caller skips
    the file (with a warning) instead of failing on one bad file among many.
    """
    path = Path(path)
    if not path.is_file():
        return {}, None
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        return {}, f"{path}: not readable JSON ({' '.join(str(exc).split())})"
    if not isinstance(data, dict):
        return {}, f"{path}: expected a JSON object, got {type(data).__name__}"
    for k in numbers:
        if data.get(k) is not None and not is_number(data[k]):
            return {}, f"{path}: '{k}' is not a number ({json.dumps(data[k])[:40]})"
    for k in number_maps:
        m = data.get(k)
        if m is not None and not (isinstance(m, dict) and all(is_number(v) for v in m.values())):
            return {}, f"{path}: '{k}' is not an object of numbers ({json.dumps(m)[:40]})"
    return data, None


def finite_or_error(arr: np.ndarray, what: str) -> np.ndarray:
    if not np.isfinite(arr).all():
        raise DynslamError(f"{what} contains NaN or infinite values")
    return arr


def group_by(items, key) -> dict:
    """``{key(item): [items...]}`` in first-seen order."""
    out: dict = {}
    for it in items:
        out.setdefault(key(it), []).append(it)
    return out
