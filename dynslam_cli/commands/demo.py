"""`dynslam demo`: a small synthetic scene rendered, run end to end and evaluated."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from dynslam_cli.commands import _common as c


def register(app: typer.Typer) -> None:
    @app.command("demo")
    def demo(
        scene: str = typer.Option("walker", "--scene", help="Synthetic scene preset to render and run (walker, crowd, "
                                  "kidnap, balloon, tracking, static)."),
        out: Optional[Path] = typer.Option(None, "--out", help="Run folder (default results/runs/synth/<scene>/dynamic, "
                                           "replaced by each demo)."),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace the run in an --out folder that holds one."),
        threads: Optional[int] = typer.Option(None, "--threads", help="Torch/numba/onnxruntime threads (default 1: "
                                              "more lose to contention on a shared machine)."),
        sets: Optional[List[str]] = c.SetOpt,
        seed: Optional[int] = typer.Option(None, "--seed", help="Random seed of the run (default run.seed)."),
        data_root: Optional[Path] = c.DataRootOpt,
        device: Optional[str] = typer.Option(None, "--device", help="auto, cpu or cuda."),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars."),
        preset: Optional[str] = typer.Option(None, "--preset", help="A configuration preset, as for `dynslam run`: "
                                             "coslam, paper, yolo-person or a file."),
    ) -> None:
        """Render a small synthetic scene (first time only), run SLAM on it in dynamic mode and report
        ATE, motion-mask IoU, mesh accuracy and speed (also written to report.md in the run folder)."""
        from dynslam_cli.run.demo import format_report, run_demo

        res = run_demo(scene, out=out, data_root=data_root, sets=list(sets or []), threads=threads,
                       device=device, seed=seed, overwrite=overwrite, progress=not quiet,
                       config_preset=preset)
        typer.echo(format_report(res), nl=False)
