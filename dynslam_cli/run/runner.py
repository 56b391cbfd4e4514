"""Running a sequence end to end into a run folder (layout in DEVELOPING.md).

``run_sequence`` opens the sequence, takes the run folder (``run/folder.py``: a lock, and a refusal
before anything is written when the folder already holds a run, unless ``overwrite`` or ``resume``),
builds the SLAM system, processes every frame through the loop of ``run/loop.py`` (static mode: every
pixel static; dynamic mode: the motion module decides which pixels are), writes checkpoints every
``run.checkpoint_every`` frames and at the end the trajectory, mesh, timing and run.json.  Every file
is written atomically; run.json says ``completed`` only after every other file is written, ``failed``
after an error and ``interrupted`` after Ctrl-C or ``stop_after`` frames.

A checkpoint records what it belongs to (``run/checkpoint.py``); ``resume`` refuses one whose
record differs and names the difference.
"""

from __future__ import annotations

import json
import random
import sys
import traceback
from contextlib import closing
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Optional

import numpy as np

from dynslam_cli.errors import DynslamError
from dynslam_cli.run import checkpoint
from dynslam_cli.run.ahead import ReadAhead
from dynslam_cli.run.environment import cpu_seconds, peak_rss_mb, versions
from dynslam_cli.run.folder import FolderLock, claim_folder, read_status
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
    for s, T, qq in zip(stamps, poses, q, strict=False):
        t = T[:3, 3]
        lines.append(f"{s} {t[0]:.7f} {t[1]:.7f} {t[2]:.7f} {qq[0]:.7f} {qq[1]:.7f} {qq[2]:.7f} {qq[3]:.7f}")
    return write_text_atomic(path, "\n".join(lines) + "\n")


def _say(progress: bool, msg: str) -> None:
    if progress:
        print(msg, file=sys.stderr, flush=True)


def run_sequence(spec: str, cfg, out_dir: Optional[Path] = None, resume: bool = False, overwrite: bool = False,
                 progress: bool = True, stop_after: int = 0) -> RunResult:
    """Run SLAM on sequence ``spec`` with the resolved config ``cfg``; see the module docstring.

    ``stop_after`` > 0 (for tests of resuming): stop, status ``interrupted``, with a checkpoint, after
    processing this many frames in this call.

    ``out_dir`` defaults to ``run.results_root/<dataset>/<name>/<mode>``.  A folder that already holds
    a run is refused unless ``overwrite`` (its run files are deleted first) or ``resume``.
    """
    from dynslam_cli.data.open import open_sequence

    mode = cfg.run.mode
    if mode not in MODES:
        raise DynslamError(f"run.mode must be static or dynamic, got '{mode}'")
    device = select_device(cfg.run.device)
    threads = set_threads(cfg.run.threads)
    seq = open_sequence(spec, cfg, progress=progress)
    if len(seq) == 0:
        raise DynslamError(f"sequence {spec} has no frames (after start/frames/stride)")
    out = Path(out_dir) if out_dir is not None else default_out_dir(cfg, seq.dataset, seq.name, mode)
    identity = checkpoint.run_identity(spec, seq, cfg, device.type)
    with FolderLock(out):
        claim_folder(out, resume=resume, overwrite=overwrite)  # refuses before anything is written
        state = checkpoint.resume_state(out / "checkpoint.pt", identity) if resume else None
        run = _Run(spec, cfg, seq, out, device, threads, identity, progress)
        run.stop_after = max(0, int(stop_after))
        return run.execute(state)


class _Run:
    """One call of :func:`run_sequence` once the folder is ours: run.json, the frames, the outputs."""

    def __init__(self, spec, cfg, seq, out: Path, device, threads: int, identity: dict, progress: bool):
        self.cfg, self.seq, self.out, self.device, self.identity, self.progress = cfg, seq, out, device, identity, progress
        self.threads = int(threads)
        self.n = len(seq)
        self.ckpt, self.run_json = out / "checkpoint.pt", out / "run.json"
        self.meta = {
            "status": "running",
            "sequence": {"spec": spec, "dataset": seq.dataset, "name": seq.name,
                         "path": str(Path(seq.path).resolve()),
                         "groundtruth": None if seq.groundtruth_file is None
                         else str(Path(seq.groundtruth_file).resolve()),
                         "frames_sha256": identity["sequence"]["frames_sha256"], "depth_noise": seq.depth_noise},
            "mode": cfg.run.mode, "variant": cfg.run.mode, "frames": self.n, "device": str(device),
            "seed": int(cfg.run.seed), "threads": threads, "versions": versions(device), "started": _now(),
            "finished": None, "error": None,
        }
        self.slam = self.loop = self.bar = None
        self.stop_after = 0
        self.timings: dict = {}
        self.cpu_ms_per_frame = 0.0  # every thread's CPU time over the frames this process ran

    def execute(self, state: Optional[dict]) -> RunResult:
        from dynslam_cli.config.loader import save_config

        if state is not None:
            old = (read_status(self.out) or {}).get("started")
            self.meta["started"] = old or self.meta["started"]
        save_config(self.cfg, self.out / "config.yaml")
        write_json_atomic(self.run_json, self.meta)
        try:
            start = self._build(state)
            done = self._frames(start)
            if done < self.n:
                processed = done - start
                self.meta.update(status="interrupted", error=f"stopped after {processed} frames (stop_after)")
                write_json_atomic(self.run_json, self.meta)
                return RunResult("interrupted", self.out, done, 0.0, {"run": self.run_json, "checkpoint": self.ckpt})
            fps, paths = self._finish()
            # last: run.json says completed only once every other file is written
            # the threading layer numba really used is known only once a parallel kernel has run
            self.meta.update(status="completed", finished=_now(), frames=self.n, versions=versions(self.device))
            write_json_atomic(self.run_json, self.meta)
            return RunResult("completed", self.out, self.n, fps, paths)
        except BaseException as exc:
            self._close_bar()
            interrupted = isinstance(exc, KeyboardInterrupt)
            err = str(exc) if isinstance(exc, DynslamError) else f"{type(exc).__name__}: {exc}"
            self.meta.update(status="interrupted" if interrupted else "failed", finished=_now(),
                             error="interrupted (Ctrl-C or SIGTERM)" if interrupted else err)
            try:
                write_json_atomic(self.run_json, self.meta)
            except OSError:
                pass
            if not isinstance(exc, (DynslamError, KeyboardInterrupt, OSError)):
                traceback.print_exc(file=sys.stderr)
            raise

    def _build(self, state: Optional[dict]) -> int:
        """The SLAM system (and motion loop), restored from ``state`` when resuming; the first frame to run."""
        import torch

        from dynslam_cli.run.loop import TIMED, FrameLoop
        from dynslam_cli.slam.system import SLAM

        cfg, seq = self.cfg, self.seq
        seed_everything(int(cfg.run.seed))
        if self.device.type == "cuda":  # peak_gpu_mb is this run's, also after other runs in the process
            torch.cuda.reset_peak_memory_stats(self.device)
        self.slam = SLAM(cfg, seq.intrinsics, self.device, bounds=sequence_bounds(cfg, seq), depth_noise=seq.depth_noise)
        masks = self.out / "masks" if cfg.run.save_masks else None
        self.loop = FrameLoop(cfg, seq.intrinsics, self.slam, self.device, masks)
        if self.loop.mm is not None:  # what computed the embeddings (runtimes round differently)
            enc = self.loop.mm.encoder
            self.meta["encoder"] = f"{enc.name} on {enc.backend}"
        self.timings = {k: [] for k in TIMED}
        if state is None:
            return 0
        self.slam.load_state_dict(state["slam"])
        self.loop.load_state_dict(state["loop"])
        self.timings = state["timings"]
        for k in TIMED:  # a checkpoint from before a timed part existed: zeros for the frames it holds
            self.timings.setdefault(k, [0.0] * len(self.timings["frame"]))
        torch.set_rng_state(state["torch_rng"])
        np.random.set_state(state["np_rng"])
        random.setstate(state["py_rng"])
        return int(state["next_frame"])

    def _open_bar(self, initial: int) -> None:
        """The bar starts after frame 0's map initialisation, so its rate and ETA are those of ordinary frames."""
        if self.progress:
            from tqdm import tqdm

            self.bar = tqdm(total=self.n, initial=initial, desc=f"{self.seq.dataset}/{self.seq.name}", unit="f",
                            file=sys.stderr, dynamic_ncols=True)

    def _close_bar(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def _frames(self, start: int) -> int:
        """Process frames from ``start``; returns the next frame (``n`` unless stop_after stopped it)."""
        cfg, n = self.cfg, self.n
        if start == 0:
            _say(self.progress, f"initialising the map from frame 0 ({cfg.mapping.first_iters} iterations)...")
        else:
            self._open_bar(start)
        # segment + encode the next frame meanwhile, where the run has a second core for it (the same bits as in order;
        # Bonn clip, dynamic mode: 3 % faster on 2 CPU cores, 31 % after the first frame on a GPU; docs/experiments.md)
        work = self.loop.perceive if self.loop.mm is not None and self.threads >= 2 else None
        ahead = ReadAhead(self.seq, start, n, work)
        c0 = cpu_seconds()
        done = self._run_frames(ahead, start, n)
        if done > start:  # the read-ahead thread's CPU time too
            self.cpu_ms_per_frame = 1e3 * (cpu_seconds() - c0) / (done - start)
        return done

    def _run_frames(self, ahead: ReadAhead, start: int, n: int) -> int:
        """:meth:`_frames`' loop over what ``ahead`` reads (and perceives)."""
        cfg = self.cfg
        with closing(iter(ahead)) as frames:
            for i, frame, seen in frames:
                step = self.loop.process(frame, self.seq.stamps[i], seen)
                step["wait"] = ahead.waited_ms  # reading / perceiving this frame that the last did not hide
                step["frame"] += ahead.waited_ms
                for k in self.timings:
                    self.timings[k].append(float(step[k]))
                done = i + 1
                if self.progress:
                    # the dense tracking's loss; the backend's tracking has none (NaN): not shown
                    post = {"loss": f"{step['_loss']:.3f}"} if np.isfinite(step["_loss"]) else {}
                    if self.loop.mm is not None:
                        post.update(dyn=step["_dynamic"], updates=len(self.loop.records))
                    if self.bar is None:
                        self._open_bar(done)
                        self.bar.set_postfix(post)
                    else:
                        self.bar.set_postfix(post, refresh=False)
                        self.bar.update(1)
                stop = self.stop_after > 0 and done - start >= self.stop_after and done < n
                periodic = cfg.run.checkpoint_every > 0 and done % cfg.run.checkpoint_every == 0 and done < n
                if periodic or stop:
                    checkpoint.save(self.ckpt, self.slam, done, self.timings, self.identity, self.loop)
                    self.loop.write_frames(self.out / "frames.jsonl")
                    if self.loop.mm is not None:
                        self.loop.write_updates(self.out / "classifier_updates.jsonl")
                if stop:
                    self._close_bar()
                    return done
        self._close_bar()
        return n

    def _finish(self) -> tuple[float, dict]:
        """Final bundle adjustment, trajectory, mesh, timing; the checkpoint goes (unless kept)."""
        cfg, out, slam, loop = self.cfg, self.out, self.slam, self.loop
        paths = {"config": out / "config.yaml", "run": self.run_json}
        if cfg.mapping.final_iters > 0:
            _say(self.progress, f"final bundle adjustment ({cfg.mapping.final_iters} iterations)...")
        fin = slam.finish()  # mapping.final_iters of bundle adjustment (none by default)
        traj, refined = slam.final_trajectory()
        smoothing = None
        if slam.backend is not None:  # the backend's centres, smoothed over the whole sequence; the raw ones beside
            from dynslam_cli.backend.smoothing import smooth_poses

            paths["traj_unsmoothed"] = write_tum(out / "traj_unsmoothed.txt", self.seq.stamps, traj)
            traj, sm = smooth_poses(self.seq.timestamps[:len(traj)], traj)
            smoothing = {"q_m2_s3": None if np.isnan(sm.q) else sm.q,  # None: too short or no noise, not smoothed
                         "noise_sd_m": sm.noise_sd, "downweighted_frames": sm.downweighted,
                         "refined_frames": int(refined)}
        paths["traj"] = write_tum(out / "traj_est.txt", self.seq.stamps, traj)
        if slam.online is not None and len(slam.online) == len(traj):  # what a robot would have had, frame by frame
            paths["traj_online"] = write_tum(out / "traj_online.txt", self.seq.stamps, np.array(slam.online))
        if cfg.run.mesh:
            _say(self.progress, f"extracting the mesh ({cfg.run.mesh_resolution} m voxels)...")
            mesh, mesh_dropped = loop.mesh(cfg.run.mesh_resolution)
            with atomic_path(out / "mesh.ply") as tmp:
                mesh.export(tmp, file_type="ply", encoding="binary")
            paths["mesh"] = out / "mesh.ply"
        frame_ms = np.asarray(self.timings["frame"], float)
        final_ms = 0.0 if fin is None else float(fin.ms)  # counted in the overall fps
        total_s = (frame_ms.sum() + final_ms) / 1000.0
        fps = float(len(frame_ms) / total_s) if total_s > 0 else 0.0
        steady = frame_ms[1:] if len(frame_ms) > 1 else frame_ms
        timing = {
            "frames": int(len(frame_ms)), "fps": fps,
            "fps_after_first": float(len(steady) / (steady.sum() / 1000.0)) if steady.sum() > 0 else 0.0,
            "first_frame_ms": float(frame_ms[0]) if len(frame_ms) else 0.0, "final_ba_ms": final_ms,
            "median_ms": {k: float(np.median(v)) if len(v) else 0.0 for k, v in self.timings.items()},
            "mean_ms": {k: float(np.mean(v)) if len(v) else 0.0 for k, v in self.timings.items()},
            "calls": {k: int(sum(1 for x in v if x > 0)) for k, v in self.timings.items()},  # frames each part ran on
            "peak_rss_mb": peak_rss_mb(),  # the process's peak so far: frames, final BA and mesh included
            # CPU time of every thread while the frames ran (this process's frames; frame 0 included): on a machine
            # with spare cores it says how much of them the run used (cpu_ms_per_frame / mean frame ms = cores busy)
            "cpu_ms_per_frame": self.cpu_ms_per_frame,
        }
        if self.device.type == "cuda":  # what torch's allocator held at most on the GPU
            import torch

            timing["peak_gpu_mb"] = torch.cuda.max_memory_allocated(self.device) / 2.0 ** 20
        if smoothing is not None:
            timing["smoothing"] = smoothing
        paths["frames"] = loop.write_frames(out / "frames.jsonl")
        if loop.mm is not None:
            paths["updates"] = loop.write_updates(out / "classifier_updates.jsonl")
            timing["classifier_updates"] = len(loop.records)
            timing["retracked_frames"] = sum(1 for r in loop.records if r.get("retracked"))
            # rays forgotten for good (run.forget_radius), counted from the keyframes
            timing["keyframe_rays_gone"] = int(sum(int(k.gone.sum()) for k in slam.keyframes if k.gone is not None))
            if cfg.run.mesh:  # mesh vertices on surfaces the newest keyframe looking at them saw through (loop.mesh)
                timing["mesh_vertices_departed"] = mesh_dropped
        paths["timing"] = write_json_atomic(out / "timing.json", timing)
        if slam.events:
            paths["events"] = write_json_atomic(out / "tracking_events.json", slam.events)
        if self.ckpt.exists() and not cfg.run.keep_checkpoint:
            self.ckpt.unlink()
        return fps, paths
