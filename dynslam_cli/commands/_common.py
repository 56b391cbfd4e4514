"""Options shared by several commands, and config resolution from them."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

SeqOpt = typer.Option(..., "--seq", help="Sequence: tum/NAME, bonn/NAME, synth/NAME or a folder path.")
ConfigOpt = typer.Option(None, "--config", help="YAML config file layered over configs/ (same layout).")
SetOpt = typer.Option(None, "--set", help="Override a config key: section.key=value (repeatable).")
DataRootOpt = typer.Option(None, "--data-root", help="Data root for named sequences (default $DYNSLAM_DATA or data/).")
FramesOpt = typer.Option(None, "--frames", help="Use N frames (0 = all).")
StartOpt = typer.Option(None, "--start", help="First frame index.")
StrideOpt = typer.Option(None, "--stride", help="Use every S-th frame.")


def resolve_config(seq: Optional[str], config: Optional[Path], sets: Optional[List[str]],
                   data_root: Optional[Path] = None, frames: Optional[int] = None,
                   start: Optional[int] = None, stride: Optional[int] = None):
    """The resolved Config for a sequence, with CLI cut options applied as overrides."""
    from dynslam_cli.config import load_config
    from dynslam_cli.data.names import identify

    sid = identify(seq) if seq else None
    overrides = list(sets or [])
    if data_root is not None:
        overrides.append(f"data.root={data_root}")
    for key, value in (("frames", frames), ("start", start), ("stride", stride)):
        if value is not None:
            overrides.append(f"data.{key}={value}")
    return load_config(sid.dataset if sid else None, sid.name if sid else None, config, overrides)
