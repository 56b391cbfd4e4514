"""`dynslam ablate`, `dynslam tables`, `dynslam plot`: experiments over many runs."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from dynslam_cli.commands import _common as c


def register(app: typer.Typer) -> None:
    @app.command("ablate")
    def ablate(
        seq: str = typer.Option(..., "--seq", help="Comma list of sequences (tum/NAME, bonn/NAME, synth/NAME, folders)."),
        mode: str = typer.Option("dynamic", "--mode", help="Comma list of modes: dynamic,static."),
        encoder: Optional[str] = typer.Option(None, "--encoder", help="Comma list of encoders (motion.encoder)."),
        segmenter: Optional[str] = typer.Option(None, "--segmenter", help="Comma list of segmenters (motion.segmenter)."),
        replay: Optional[str] = typer.Option(None, "--replay", help="on,off (motion.replay)."),
        prior: Optional[str] = typer.Option(None, "--prior", help="on,off; 'on' uses --prior-file (motion.prior)."),
        prior_file: Optional[Path] = typer.Option(None, "--prior-file", help="Prior classifier file for --prior on."),
        seeds: str = typer.Option("0", "--seeds", help="Comma list of seeds (run.seed)."),
        name: str = typer.Option("default", "--name", help="Ablation name: results go to <results>/<name>/<cell-id>/."),
        frames: Optional[int] = c.FramesOpt,
        config: Optional[Path] = c.ConfigOpt,
        preset: Optional[str] = c.PresetOpt,
        sets: Optional[List[str]] = c.SetOpt,
        data_root: Optional[Path] = c.DataRootOpt,
        results: Path = typer.Option(Path("results/ablations"), "--results", help="Folder of ablations."),
        dry_run: bool = typer.Option(False, "--dry-run", help="Print the cells (one per line) and stop."),
        executor: str = typer.Option("local", "--executor", help="local (process pool) or ray."),
        jobs: int = typer.Option(1, "--jobs", help="Local executor: parallel cells (threads divided among them)."),
        threads: Optional[int] = typer.Option(None, "--threads", help="run.threads of each cell (default: the CPUs "
                                              "divided by --jobs, or --cpus-per-cell with Ray)."),
        address: Optional[str] = typer.Option(None, "--address", help="Ray cluster address (default: a local instance)."),
        num_cpus: Optional[int] = typer.Option(None, "--num-cpus", help="Ray: CPUs of the local instance (default all)."),
        cpus_per_cell: float = typer.Option(1.0, "--cpus-per-cell", help="Ray: num_cpus of each cell's task."),
        gpus_per_cell: float = typer.Option(0.0, "--gpus-per-cell", help="Ray: num_gpus of each cell's task."),
    ) -> None:
        """Run a grid of configurations, one evaluated run per cell; finished cells are skipped.

        A cell's id ends in a hash of everything that changes its result (resolved config, sequence,
        frame cut, seed): other options make other cells, the same options resume the grid.
        """
        from dynslam_cli.eval import ablate as ab

        cells = ab.build_grid(ab.split_list(seq), ab.split_list(mode), ab.split_list(encoder),
                              ab.split_list(segmenter), ab.split_list(replay), ab.split_list(prior),
                              ab.split_list(seeds), str(prior_file) if prior_file else None, list(sets or []))
        cells = ab.key_cells(cells, str(config) if config else None, str(data_root) if data_root else None, frames,
                             preset)
        if dry_run:
            for cell in cells:
                done = ab.cell_done(results / name / cell.id, cell.key)
                typer.echo(f"{cell.id}{'  (done, skipped)' if done else ''}  {' '.join(cell.overrides)}")
            return

        def progress(d: dict) -> None:
            rm = "" if d.get("ate_rmse_m") is None else f" ATE {d['ate_rmse_m']:.4f} m"
            err = f" error: {d['error']}" if d.get("error") else ""
            typer.echo(f"[{d['status']}] {d['id']}{rm}{err}")

        res = ab.ablate(cells, name, results, executor=executor, jobs=jobs, address=address,
                        config_file=str(config) if config else None, data_root=str(data_root) if data_root else None,
                        frames=frames, cpus_per_cell=cpus_per_cell, gpus_per_cell=gpus_per_cell,
                        num_cpus=num_cpus, on_done=progress, threads=threads, preset=preset)
        typer.echo(res.summary_md, nl=False)
        typer.echo(f"{len(res.cells)} cells, {res.failed} failed; summary in {res.root}/summary.md")
        if res.failed:
            raise typer.Exit(1)

    @app.command("tables")
    def tables(
        results: Path = typer.Option(Path("results"), "--results", help="Results folder (runs/ and ablations/)."),
        out: Optional[Path] = typer.Option(None, "--out", help="Output folder (default <results>/tables)."),
        published: Optional[Path] = typer.Option(None, "--published", help="Published numbers (default configs/published.yaml)."),
        plots: bool = typer.Option(True, "--plots/--no-plots", help="Also write the PNG plots."),
        include_incomplete: bool = typer.Option(False, "--include-incomplete",
                                                help="Also use runs whose run.json is not 'completed'."),
    ) -> None:
        """Paper-style tables (CSV, Markdown, LaTeX) and plots from result files only.

        Runs that are not completed and unreadable result files are skipped, each with a warning.
        """
        from dynslam_cli.eval.tables import make_tables

        r = make_tables(results, out, published, plots, include_incomplete)
        for w in r.warnings:
            typer.echo(f"warning: {w}", err=True)
        what = "runs" if include_incomplete else "completed runs"
        typer.echo(f"{r.runs} {what} -> {len(r.files)} files in {r.out}")

    @app.command("plot")
    def plot(
        run_dir: Path = typer.Argument(..., help="Run folder."),
        frames: Optional[str] = typer.Option(
            None, "--frames", help="Comma list of mask timestamps, matched numerically (default 4 evenly spread)."),
        index: Optional[str] = typer.Option(None, "--index", help="Comma list of frame indices in the run (0 = data.start)."),
        out: Optional[Path] = typer.Option(None, "--out", help="PNG to write (default RUN_DIR/montage.png)."),
    ) -> None:
        """Montage of input RGB / input depth / rendered depth / motion mask at chosen frames of a run with saved masks."""
        from dynslam_cli.errors import DynslamError
        from dynslam_cli.eval import runs
        from dynslam_cli.eval.plots import montage

        d = runs.require_run_dir(run_dir)
        chosen = [s.strip() for s in frames.split(",") if s.strip()] if frames else None
        indices = None
        if index:
            try:
                indices = [int(s) for s in index.split(",") if s.strip()]
            except ValueError:
                raise DynslamError(f"--index takes comma-separated frame indices, got '{index}'") from None
        p = montage(d, out or d / "montage.png", chosen, indices=indices)
        if p is None:
            raise DynslamError(f"run {d} saved no masks (masks/<ts>.png); run with run.save_masks=true")
        typer.echo(f"wrote {p}")
