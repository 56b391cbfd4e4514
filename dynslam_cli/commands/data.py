"""`dynslam info` and `dynslam download`."""

from __future__ import annotations

from pathlib import Path

import typer

from dynslam_cli.commands import _common as c


def register(app: typer.Typer) -> None:
    @app.command("info")
    def info(
        seq: str = c.SeqOpt,
        data_root: Path | None = c.DataRootOpt,
        config: Path | None = c.ConfigOpt,
        sets: list[str] | None = c.SetOpt,
        frames: int | None = c.FramesOpt,
        start: int | None = c.StartOpt,
        stride: int | None = c.StrideOpt,
        as_json: bool = typer.Option(False, "--json", help="Print the information as JSON."),
    ) -> None:
        """Describe a sequence: frames, camera, depth statistics, ground truth."""
        import json

        from dynslam_cli.data.info import sequence_info

        cfg = c.resolve_config(seq, config, sets, data_root, frames, start, stride)
        result = sequence_info(seq, cfg)
        if as_json:
            typer.echo(json.dumps(result.to_dict(), indent=2))
        else:
            typer.echo(result.format(), nl=False)

    @app.command("download")
    def download(
        names: list[str] = typer.Argument(..., help="tum/NAME, bonn/NAME or bonn/reference (several allowed)."),
        data_root: Path | None = c.DataRootOpt,
        base_url: str | None = typer.Option(
            None, "--base-url", help="Mirror: replaces scheme and server of the official URLs "
            "(default $DYNSLAM_DOWNLOAD_BASE)."),
        quiet: bool = typer.Option(False, "--quiet", help="No progress bar."),
    ) -> None:
        """Download and extract official TUM RGB-D / Bonn RGB-D Dynamic archives into the data root."""
        from dynslam_cli.data.download import download as run_download
        from dynslam_cli.data.open import data_root as resolve_root

        cfg = c.resolve_config(None, None, None, data_root)
        for r in run_download(names, resolve_root(cfg), base_url=base_url, progress=not quiet):
            if r.status == "present":
                typer.echo(f"{r.key}: already present in {r.folder}")
            else:
                typer.echo(f"{r.key}: {r.bytes / 1e6:.1f} MB downloaded, extracted to {r.folder}")
