"""Helpers for config dataclasses: every field carries its help text (shown by `config show`) and,
for numbers and closed sets of strings, the rule its value must follow.

Rules are checked once, by ``config.loader.validate_config`` after every layer and ``--set`` is
merged: ``opt(0.1, "...", above=0)`` (> 0), ``min=0`` (>= 0), ``min=0, below=1`` ([0, 1)),
``choices=("cpu", "cuda")``, ``also=(-1,)`` (a sentinel allowed outside the range),
``check=(predicate, "odd")`` for anything else.  A dataclass may add cross-field rules in a
``validate(self, key)`` method yielding one message per violation (``key("near")`` is the full
key, e.g. ``map.near``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Callable, Optional


@dataclass(frozen=True)
class Rule:
    """What a field's value must be; ``violation`` says how a value breaks it (None = valid)."""

    min: Optional[float] = None  # value >= min
    max: Optional[float] = None  # value <= max
    above: Optional[float] = None  # value > above
    below: Optional[float] = None  # value < below
    choices: Optional[tuple] = None
    also: tuple = ()  # sentinels valid whatever the range (e.g. -1 = "same as ...")
    check: Optional[tuple[Callable[[Any], bool], str]] = None

    def describe(self) -> str:
        """``> 0``, ``in [0, 1)``, ``one of a, b``, ``>= 0 or -1``."""
        if self.choices is not None:
            text = "one of " + ", ".join(str(c) for c in self.choices)
        else:
            lo = (f"[{_num(self.min)}" if self.min is not None
                  else f"({_num(self.above)}" if self.above is not None else None)
            hi = (f"{_num(self.max)}]" if self.max is not None
                  else f"{_num(self.below)})" if self.below is not None else None)
            if lo and hi:
                text = f"in {lo}, {hi}"
            elif lo:
                text = (">= " if lo[0] == "[" else "> ") + lo[1:]
            elif hi:
                text = ("<= " if hi[-1] == "]" else "< ") + hi[:-1]
            else:
                text = "a finite number"
            if self.check is not None:
                text = self.check[1] if text == "a finite number" else f"{text} and {self.check[1]}"
        if self.also:
            text += " or " + " or ".join(_num(a) for a in self.also)
        return text

    def violation(self, value: Any) -> Optional[str]:
        if value in self.also and not isinstance(value, bool):
            return None
        if self.choices is not None:
            return None if value in self.choices else f"must be {self.describe()} (got {value!r})"
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            return None  # the type was checked when merging; None for optional fields
        ok = (math.isfinite(value)
              and (self.min is None or value >= self.min) and (self.max is None or value <= self.max)
              and (self.above is None or value > self.above) and (self.below is None or value < self.below)
              and (self.check is None or bool(self.check[0](value))))
        return None if ok else f"must be {self.describe()} (got {value!r})"


def _num(v: Any) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def opt(default: Any, help: str, *, min: Optional[float] = None,  # noqa: A002 - names read best at call sites
        max: Optional[float] = None, above: Optional[float] = None, below: Optional[float] = None,  # noqa: A002
        choices: Optional[tuple] = None, also: tuple = (),
        check: Optional[tuple[Callable[[Any], bool], str]] = None) -> Any:
    """A dataclass field with a default, a help string and an optional value rule (mutable
    defaults are copied)."""
    meta: dict[str, Any] = {"help": help}
    if any(x is not None for x in (min, max, above, below, choices, check)):
        meta["rule"] = Rule(min, max, above, below, tuple(choices) if choices is not None else None,
                            tuple(also), check)
    if isinstance(default, (list, dict, set)):
        return dataclasses.field(default_factory=lambda d=default: _copy(d), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def rule_of(f: dataclasses.Field) -> Optional[Rule]:
    return f.metadata.get("rule")


def numbers(value: Any, n: Optional[int] = None) -> Optional[list[float]]:
    """``value`` as a list of finite numbers (of length ``n``), else None (for ``validate`` rules)."""
    if not isinstance(value, (list, tuple)) or (n is not None and len(value) != n):
        return None
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value):
        return None
    return [float(v) for v in value]


def _copy(value: Any) -> Any:
    import copy

    return copy.deepcopy(value)
