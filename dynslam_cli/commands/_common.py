"""Options shared by several commands, and config resolution from them."""

from __future__ import annotations

import typer

from dynslam_cli.config.resolve import resolve_config  # noqa: F401 - the commands use c.resolve_config

SeqOpt = typer.Option(..., "--seq", help="Sequence: tum/NAME, bonn/NAME, synth/NAME or a folder path.")
ConfigOpt = typer.Option(None, "--config", help="YAML config file layered over configs/ (same layout).")
PresetOpt = typer.Option(None, "--preset", help="A named variant of the algorithm: coslam (the paper's static "
                         "baseline), paper (dense tracking + neural BA + forgetting, as published), yolo-person, or "
                         "any file in configs/presets/ (or a YAML path); layered after the dataset file, before "
                         "--config.")
SetOpt = typer.Option(None, "--set", help="Override a config key: section.key=value (repeatable).")
DataRootOpt = typer.Option(None, "--data-root", help="Data root for named sequences (default $DYNSLAM_DATA or data/).")
FramesOpt = typer.Option(None, "--frames", help="Use N frames (0 = all).")
StartOpt = typer.Option(None, "--start", help="First frame index.")
StrideOpt = typer.Option(None, "--stride", help="Use every S-th frame.")
