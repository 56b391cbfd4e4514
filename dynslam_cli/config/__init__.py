"""Typed configuration: dataclasses per part, YAML files in `configs/`, `--set a.b=v` overrides.

Exports are loaded on first use: the per-layer config modules import ``config.fields`` and must
not pull in the loader (which imports them back through the schema).
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "Config": "dynslam_cli.config.schema",
    "apply_overrides": "dynslam_cli.config.loader",
    "config_from_file": "dynslam_cli.config.loader",
    "config_to_dict": "dynslam_cli.config.loader",
    "config_to_yaml": "dynslam_cli.config.loader",
    "configs_dir": "dynslam_cli.config.loader",
    "load_config": "dynslam_cli.config.loader",
    "save_config": "dynslam_cli.config.loader",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'dynslam_cli.config' has no attribute {name!r}")
