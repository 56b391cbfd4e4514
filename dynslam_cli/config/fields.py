"""Helpers for config dataclasses: every field carries its help text (shown by `config show`)."""

from __future__ import annotations

import dataclasses
from typing import Any


def opt(default: Any, help: str) -> Any:  # noqa: A002 - 'help' reads best at call sites
    """A dataclass field with a default and a help string (mutable defaults are copied)."""
    if isinstance(default, (list, dict, set)):
        return dataclasses.field(default_factory=lambda d=default: _copy(d), metadata={"help": help})
    return dataclasses.field(default=default, metadata={"help": help})


def _copy(value: Any) -> Any:
    import copy

    return copy.deepcopy(value)
