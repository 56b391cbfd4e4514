"""`dynslam config show`."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from dynslam_cli.commands import _common as c


def register(app: typer.Typer) -> None:
    from dynslam_cli.cli import make_group

    group = make_group("Inspect the configuration.")

    @group.command("show")
    def show(
        seq: Optional[str] = typer.Option(None, "--seq", help="Resolve for this sequence (its dataset file and "
                                          "per-sequence entries)."),
        config: Optional[Path] = c.ConfigOpt,
        preset: Optional[str] = c.PresetOpt,
        sets: Optional[List[str]] = c.SetOpt,
        plain: bool = typer.Option(False, "--plain", help="No help comments."),
    ) -> None:
        """Print the resolved configuration as YAML, each key with its help."""
        from dynslam_cli.config import config_to_yaml

        cfg = c.resolve_config(seq, config, sets, preset=preset)
        typer.echo(config_to_yaml(cfg, comments=not plain), nl=False)

    app.add_typer(group, name="config")
