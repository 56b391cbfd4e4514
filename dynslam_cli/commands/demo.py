"""`dynslam demo`: a small synthetic scene rendered and run end to end."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dynslam_cli.commands import _common as c

# The demo: a small synthetic scene (rendered on first use) that runs in about a minute or two on
# 2 CPU cores: 100 frames at 320x240 with Co-SLAM's iteration counts (first-frame mapping shortened).
DEMO_SETS = ["synth.width=320", "synth.height=240", "synth.frames=100", "mapping.first_iters=300",
             "tracking.ignore_border=10"]


def register(app: typer.Typer) -> None:
    @app.command("demo")
    def demo(
        preset: str = typer.Option("walker", "--preset", help="Synthetic preset to render and run."),
        out: Optional[Path] = typer.Option(None, "--out", help="Run folder (default results/runs/synth/<scene>/<mode>)."),
        data_root: Optional[Path] = c.DataRootOpt,
        device: Optional[str] = typer.Option(None, "--device", help="auto, cpu or cuda."),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
    ) -> None:
        """Render a small synthetic scene (first time only) and run SLAM on it in dynamic mode."""
        spec = f"synth/{preset}"
        extra = list(DEMO_SETS) + ([f"run.device={device}"] if device else [])
        cfg = c.resolve_config(spec, None, extra, data_root)
        cfg.run.mode = "dynamic"
        from dynslam_cli.run.runner import run_sequence

        res = run_sequence(spec, cfg, out_dir=out, progress=not quiet)
        typer.echo(f"demo ({cfg.run.mode} mode) on {spec}: {res.frames} frames, {res.fps:.2f} fps")
        typer.echo(f"results in {res.out_dir}: traj_est.txt, mesh.ply, timing.json, run.json")
        typer.echo(f"evaluate with: dynslam eval-ate {res.out_dir}")
