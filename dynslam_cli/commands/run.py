"""`dynslam run`: one sequence into a run folder."""

from __future__ import annotations

import contextlib
import signal
import threading
from pathlib import Path
from typing import List, Optional

import typer

from dynslam_cli.commands import _common as c
from dynslam_cli.run.folder import EVAL_FILES, RUN_DIRS, RUN_FILES

OVERWRITE_HELP = (f"Replace a run already in the folder: first deletes its {', '.join(RUN_FILES)}, the eval outputs "
                  f"({', '.join(EVAL_FILES)}) and {' and '.join(d + '/' for d in RUN_DIRS)}. Other files in the "
                  f"folder are kept. Without it (or --resume) a folder holding a run is refused.")


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """SIGTERM (kill, timeout, a scheduler) ends the run like Ctrl-C: run.json says interrupted and the
    folder's lock is released."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def _raise(signum, frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, _raise)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _mode(requested: Optional[str], cfg) -> str:
    from dynslam_cli.errors import DynslamError

    mode = requested or cfg.run.mode
    if mode not in ("static", "dynamic"):
        raise DynslamError(f"--mode must be static or dynamic, got '{mode}'")
    return mode


def register(app: typer.Typer) -> None:
    @app.command("run")
    def run(
        seq: str = c.SeqOpt,
        mode: Optional[str] = typer.Option(None, "--mode", help="static or dynamic (default: run.mode of the config)."),
        out: Optional[Path] = typer.Option(None, "--out", help="Run folder (default results/runs/<dataset>/<sequence>/<mode>)."),
        frames: Optional[int] = c.FramesOpt,
        start: Optional[int] = c.StartOpt,
        stride: Optional[int] = c.StrideOpt,
        config: Optional[Path] = c.ConfigOpt,
        preset: Optional[str] = c.PresetOpt,
        sets: Optional[List[str]] = c.SetOpt,
        device: Optional[str] = typer.Option(None, "--device", help="auto, cpu or cuda (default run.device)."),
        seed: Optional[int] = typer.Option(None, "--seed", help="Random seed (default run.seed)."),
        resume: bool = typer.Option(False, "--resume", help="Continue from the run folder's checkpoint.pt (same "
                                    "sequence, config and code version as the checkpoint's, else refused)."),
        overwrite: bool = typer.Option(False, "--overwrite", help=OVERWRITE_HELP),
        threads: Optional[int] = typer.Option(None, "--threads", help="Torch/numba threads (sets run.threads; "
                                              "0 = all cores)."),
        save_masks: bool = typer.Option(False, "--save-masks", help="Write per-frame motion masks (dynamic mode)."),
        data_root: Optional[Path] = c.DataRootOpt,
        quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar or phase lines."),
        stop_after: int = typer.Option(0, "--stop-after", hidden=True, min=0,
                                       help="Stop (interrupted, with a checkpoint) after N frames: for tests of --resume."),
    ) -> None:
        """Run SLAM on one sequence and write the run folder (trajectory, mesh, timing, run.json)."""
        from dynslam_cli.errors import DynslamError

        for name, v, lo in (("--frames", frames, 0), ("--start", start, 0), ("--stride", stride, 1),
                            ("--threads", threads, 0)):
            if v is not None and v < lo:
                raise DynslamError(f"{name} must be >= {lo}, got {v}")
        extra = []
        if device is not None:
            extra.append(f"run.device={device}")
        if seed is not None:
            extra.append(f"run.seed={seed}")
        if save_masks:
            extra.append("run.save_masks=true")
        if threads is not None:
            extra.append(f"run.threads={threads}")
        cfg = c.resolve_config(seq, config, list(sets or []) + extra, data_root, frames, start, stride, preset=preset)
        cfg.run.mode = _mode(mode, cfg)

        from dynslam_cli.run.runner import run_sequence

        with _sigterm_as_interrupt():
            res = run_sequence(seq, cfg, out_dir=out, resume=resume, overwrite=overwrite, progress=not quiet,
                               stop_after=stop_after)
        if res.status != "completed":
            typer.echo(f"run {res.status} after {res.frames} frames -> {res.out_dir} (continue with --resume)")
            return
        typer.echo(f"run completed: {res.frames} frames, {res.fps:.2f} fps -> {res.out_dir}")
