"""Running a sequence end to end into a run folder (layout in DEVELOPING.md).

``run_sequence`` opens the sequence, builds the SLAM system, processes every frame (static mode:
Co-SLAM; dynamic mode: the motion module of ``run/dynamic.py`` decides which pixels are static),
writes checkpoints every ``run.checkpoint_every`` frames and at the end the trajectory, mesh,
timing and run.json.  Every file is written atomically; run.json says ``completed`` only at the end.
"""

from __future__ import annotations

import json
import platform
import random
import sys
import time
import traceback
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Optional

import numpy as np

from dynslam_cli.errors import DynslamError
from dynslam_cli.utils.io import atomic_path, write_json_atomic, write_text_atomic
from dynslam_cli.utils.threads import seed_everything, set_threads

MODES = ("static", "dynamic")


@dataclass
class RunResult:
    status: str               # completed | failed | interrupted
    out_dir: Path
    frames: int
    fps: float
    paths: dict = field(default_factory=dict)
    ate_hint: Optional[str] = None


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def select_device(name: str):
    import torch

    name = (name or "auto").lower()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda":
        if not torch.cuda.is_available():
            raise DynslamError("--device cuda requested but CUDA is not available (use --device auto or cpu)")
        return torch.device("cuda")
    if name == "cpu":
        return torch.device("cpu")
    raise DynslamError(f"unknown device '{name}': use auto, cpu or cuda")


def versions() -> dict:
    import torch

    out = {"python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__}
    try:
        from importlib.metadata import version

        out["dynslam"] = version("dynslam")
    except Exception:
        pass
    try:
        import numba

        out["numba"] = numba.__version__
        try:
            out["numba_threading_layer"] = numba.threading_layer()
        except ValueError:  # no parallel kernel has run yet
            out["numba_threading_layer"] = str(numba.config.THREADING_LAYER)
    except Exception:
        pass
    return out


def default_out_dir(cfg, dataset: str, name: str, variant: str) -> Path:
    return Path(cfg.run.results_root) / dataset / name / variant


def sequence_bounds(cfg, seq):
    """``map.bounds`` when set; else a synthetic scene's room from synth.json ("room" or "bounds":
    [[xmin,ymin,zmin],[xmax,ymax,zmax]]) plus 0.1 m; else None (automatic from the first frame)."""
    if cfg.map.bounds is not None:
        return cfg.map.bounds
    meta = Path(seq.path) / "synth.json"
    if meta.is_file():
        try:
            d = json.loads(meta.read_text())
        except ValueError:
            return None
        room = d.get("room") or d.get("bounds")
        if room is not None:
            b = np.asarray(room, float)
            if b.shape == (2, 3):
                return [list(b[0] - 0.1), list(b[1] + 0.1)]
    return None


def write_tum(path: Path, stamps: list[str], poses: np.ndarray) -> Path:
    from scipy.spatial.transform import Rotation

    lines = ["# timestamp tx ty tz qx qy qz qw (camera-to-world)"]
    q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x y z w
    for s, T, qq in zip(stamps, poses, q):
        t = T[:3, 3]
        lines.append(f"{s} {t[0]:.7f} {t[1]:.7f} {t[2]:.7f} {qq[0]:.7f} {qq[1]:.7f} {qq[2]:.7f} {qq[3]:.7f}")
    return write_text_atomic(path, "\n".join(lines) + "\n")


def _save_checkpoint(path: Path, slam, next_frame: int, timings: dict, cfg_yaml: str, dynamic=None) -> None:
    import torch

    state = {"slam": slam.state_dict(), "next_frame": next_frame, "timings": timings, "config": cfg_yaml,
             "torch_rng": torch.get_rng_state(), "np_rng": np.random.get_state(), "py_rng": random.getstate(),
             "dynamic": None if dynamic is None else dynamic.state_dict()}
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def _load_checkpoint(path: Path) -> dict:
    import torch

    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:
        raise DynslamError(f"cannot read checkpoint {path}: {exc}") from None


def run_sequence(spec: str, cfg, out_dir: Optional[Path] = None, resume: bool = False,
                 progress: bool = True) -> RunResult:
    """Run SLAM on sequence ``spec`` with the resolved config ``cfg``; see the module docstring."""
    import torch

    from dynslam_cli.config.loader import config_to_yaml, save_config
    from dynslam_cli.data.open import open_sequence

    mode = cfg.run.mode
    if mode not in MODES:
        raise DynslamError(f"run.mode must be static or dynamic, got '{mode}'")
    device = select_device(cfg.run.device)
    threads = set_threads(cfg.run.threads)
    seq = open_sequence(spec, cfg, progress=progress)
    n = len(seq)
    if n == 0:
        raise DynslamError(f"sequence {spec} has no frames (after start/frames/stride)")
    variant = mode
    out = Path(out_dir) if out_dir is not None else default_out_dir(cfg, seq.dataset, seq.name, variant)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / "checkpoint.pt"
    run_json = out / "run.json"
    cfg_yaml = config_to_yaml(cfg)
    state = None
    if resume:
        if not ckpt.is_file():
            raise DynslamError(f"--resume: no checkpoint.pt in {out}")
        state = _load_checkpoint(ckpt)
        if state.get("config") != cfg_yaml:
            raise DynslamError(f"--resume: the config differs from the checkpoint's in {out} (resume with the same options)")
    started = _now()
    meta = {
        "status": "running",
        "sequence": {"spec": spec, "dataset": seq.dataset, "name": seq.name, "path": str(Path(seq.path).resolve()),
                     "groundtruth": None if seq.groundtruth_file is None else str(Path(seq.groundtruth_file).resolve())},
        "mode": mode, "variant": variant, "frames": n, "device": str(device), "seed": int(cfg.run.seed),
        "threads": threads, "versions": versions(), "started": started, "finished": None, "error": None,
    }
    if resume and run_json.is_file():
        try:
            meta["started"] = json.loads(run_json.read_text()).get("started", started)
        except (OSError, ValueError):
            pass
    save_config(cfg, out / "config.yaml")
    write_json_atomic(run_json, meta)

    from dynslam_cli.slam.system import SLAM

    seed_everything(int(cfg.run.seed))
    slam = SLAM(cfg, seq.intrinsics, device, bounds=sequence_bounds(cfg, seq))
    loop = None
    if mode == "dynamic":
        from dynslam_cli.run.dynamic import DynamicLoop

        loop = DynamicLoop(cfg, seq.intrinsics, slam, device, out / "masks" if cfg.run.save_masks else None)
    timings: dict = {"track": [], "map": [], "frame": []}
    if loop is not None:
        timings = {k: [] for k in ("segment", "encode", "classify", "track", "render", "check", "update", "map", "frame")}
    updates_path = out / "classifier_updates.jsonl"
    start_frame = 0
    if state is not None:
        slam.load_state_dict(state["slam"])
        if loop is not None:
            loop.load_state_dict(state["dynamic"])
        timings = state["timings"]
        start_frame = int(state["next_frame"])
        torch.set_rng_state(state["torch_rng"])
        np.random.set_state(state["np_rng"])
        random.setstate(state["py_rng"])
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n, initial=start_frame, desc=f"{seq.dataset}/{seq.name}", unit="f", file=sys.stderr,
                   dynamic_ncols=True)
    t_run = time.perf_counter()
    processed = 0
    try:
        for i in range(start_frame, n):
            frame = seq[i]
            if loop is None:
                r = slam.process(frame)
                step = {"track": r.track.ms, "map": 0.0 if r.map is None else r.map.ms, "frame": r.ms,
                        "_loss": r.track.loss}
            else:
                step = loop.process(frame, seq.stamps[i])
            for k in timings:
                timings[k].append(float(step[k]))
            processed += 1
            if bar is not None:
                el = time.perf_counter() - t_run
                post = {"fps": f"{processed / el:.2f}", "loss": f"{step['_loss']:.3f}"}
                if loop is not None:
                    post.update(dyn=step["_dynamic"], updates=len(loop.records))
                bar.set_postfix(post)
                bar.update(1)
            done = i + 1
            stop = cfg.run.stop_after > 0 and processed >= cfg.run.stop_after and done < n
            periodic = cfg.run.checkpoint_every > 0 and done % cfg.run.checkpoint_every == 0 and done < n
            if periodic or stop:
                _save_checkpoint(ckpt, slam, done, timings, cfg_yaml, loop)
                if loop is not None:
                    loop.write_updates(updates_path)
            if stop:
                meta.update(status="interrupted", error=f"stopped after {processed} frames (run.stop_after)")
                write_json_atomic(run_json, meta)
                return RunResult("interrupted", out, done, 0.0, {"run": run_json, "checkpoint": ckpt})
        if bar is not None:
            bar.close()
        paths = {"config": out / "config.yaml", "run": run_json}
        fin = slam.finish()  # mapping.final_iters of bundle adjustment (none by default)
        poses = slam.trajectory()
        paths["traj"] = write_tum(out / "traj_est.txt", seq.stamps, poses)
        if cfg.run.mesh:
            mesh = slam.extract_mesh(cfg.run.mesh_resolution)
            with atomic_path(out / "mesh.ply") as tmp:
                mesh.export(tmp, file_type="ply", encoding="binary")
            paths["mesh"] = out / "mesh.ply"
        frame_ms = np.asarray(timings["frame"], float)
        final_ms = 0.0 if fin is None else float(fin.ms)  # counted in the overall fps
        total_s = (frame_ms.sum() + final_ms) / 1000.0
        fps = float(len(frame_ms) / total_s) if total_s > 0 else 0.0
        steady = frame_ms[1:] if len(frame_ms) > 1 else frame_ms
        timing = {
            "frames": int(len(frame_ms)), "fps": fps,
            "fps_after_first": float(len(steady) / (steady.sum() / 1000.0)) if steady.sum() > 0 else 0.0,
            "first_frame_ms": float(frame_ms[0]) if len(frame_ms) else 0.0, "final_ba_ms": final_ms,
            "median_ms": {k: float(np.median(v)) if len(v) else 0.0 for k, v in timings.items()},
            "mean_ms": {k: float(np.mean(v)) if len(v) else 0.0 for k, v in timings.items()},
        }
        if loop is not None:
            paths["updates"] = loop.write_updates(updates_path)
            timing["classifier_updates"] = len(loop.records)
            timing["retracked_frames"] = sum(1 for r in loop.records if r.get("retracked"))
            # rays forgotten for good (run.forget_radius, run.carve_margin), counted from the keyframes
            timing["keyframe_rays_gone"] = int(sum(int(k.gone.sum()) for k in slam.keyframes if k.gone is not None))
        paths["timing"] = write_json_atomic(out / "timing.json", timing)
        if slam.events:
            write_json_atomic(out / "tracking_events.json", slam.events)
        if ckpt.exists() and not cfg.run.keep_checkpoint:
            ckpt.unlink()
        meta.update(status="completed", finished=_now(), frames=n)
        write_json_atomic(run_json, meta)
        return RunResult("completed", out, n, fps, paths)
    except BaseException as exc:
        if bar is not None:
            bar.close()
        meta.update(status="failed", finished=_now(),
                    error=str(exc) if isinstance(exc, DynslamError) else f"{type(exc).__name__}: {exc}")
        try:
            write_json_atomic(run_json, meta)
        except OSError:
            pass
        if not isinstance(exc, (DynslamError, KeyboardInterrupt)):
            traceback.print_exc(file=sys.stderr)
        raise
