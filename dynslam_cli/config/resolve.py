"""The resolved Config of a sequence from the options every command shares.

Library code (the ablation executors, benchmarks) and the CLI both resolve a run's config here:
the sequence name picks the dataset file (``configs/<dataset>.yaml`` and its ``sequences:``
entries), then the preset (``configs/presets/<name>.yaml``), ``config_file``, the ``--set``
overrides, and last the data root and the frame cut (``data.start``, ``data.frames``,
``data.stride``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable, Optional


def cut_overrides(data_root: Optional[str | Path] = None, frames: Optional[int] = None,
                  start: Optional[int] = None, stride: Optional[int] = None) -> list[str]:
    """``--set`` style overrides for the options given (None = leave the config's value)."""
    out = []
    if data_root is not None:
        out.append(f"data.root={data_root}")
    for key, value in (("frames", frames), ("start", start), ("stride", stride)):
        if value is not None:
            out.append(f"data.{key}={value}")
    return out


def resolve_config(seq: Optional[str], config_file: Optional[str | Path] = None,
                   sets: Optional[Iterable[str]] = None, data_root: Optional[str | Path] = None,
                   frames: Optional[int] = None, start: Optional[int] = None, stride: Optional[int] = None,
                   preset: Optional[str | Path] = None):
    """The resolved :class:`~dynslam_cli.config.schema.Config` for sequence ``seq`` (None = no dataset).

    No data is read; unknown keys and bad values raise DynslamError.
    """
    from dynslam_cli.config.loader import load_config
    from dynslam_cli.data.names import identify

    sid = identify(seq) if seq else None
    overrides = list(sets or []) + cut_overrides(data_root, frames, start, stride)
    return load_config(sid.dataset if sid else None, sid.name if sid else None, config_file or None, overrides,
                       preset=preset or None)
