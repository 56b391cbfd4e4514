"""Data layer: frames, sequence readers (TUM, Bonn, synthetic), name resolution, download.

Kept light at import: ``open_sequence`` and the types are loaded on first use.
"""

from __future__ import annotations

from typing import Any

__all__ = ["Frame", "Intrinsics", "Sequence", "SequenceInfo", "open_sequence", "sequence_info"]

_LAZY = {
    "open_sequence": "dynslam_cli.data.open",
    "Sequence": "dynslam_cli.data.sequence",
    "Frame": "dynslam_cli.data.types",
    "Intrinsics": "dynslam_cli.data.types",
    "sequence_info": "dynslam_cli.data.info",
    "SequenceInfo": "dynslam_cli.data.info",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'dynslam_cli.data' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(module), name)
