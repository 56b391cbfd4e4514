"""Loading, merging and validating configuration.

Order of precedence (later wins):

1. dataclass defaults (``schema.Config``),
2. ``configs/base.yaml``,
3. the dataset's file (``configs/tum.yaml``, ``bonn.yaml``, ``synth.yaml``: facts about the sensor and
   the data only) -- its top-level keys, then the entries of its ``sequences:`` mapping whose glob
   pattern matches the sequence name,
4. ``--preset NAME`` (``configs/presets/NAME.yaml``, or a path): a named variant of the algorithm,
5. ``--config FILE`` (same layout as base.yaml),
6. ``--set section.key=value`` overrides (values parsed as YAML).

Unknown keys anywhere are an error that names the key, the file and the valid keys.  Once all
layers are merged, every value is checked against its field's rule (``config.fields.opt``) and
each part's cross-field rules (``validate``): ``config: map.near must be < map.far (got 2 >= 1.5)``.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import re
import types
import typing
from pathlib import Path
from typing import Any, Iterable, Optional

import yaml

from dynslam_cli.config.fields import rule_of
from dynslam_cli.config.schema import Config
from dynslam_cli.errors import DynslamError
from dynslam_cli.utils.io import write_text_atomic

DATASET_FILES = {"tum": "tum.yaml", "bonn": "bonn.yaml", "synth": "synth.yaml"}


def configs_dir() -> Path:
    """The ``configs/`` folder: the checkout's (source checkout or editable install), else the copy
    a built wheel ships inside the package as ``dynslam_cli/_configs`` (see setup.py)."""
    pkg = Path(__file__).resolve().parents[1]
    cands = (pkg.parent / "configs", pkg / "_configs")
    for cand in cands:
        if (cand / "base.yaml").is_file():
            return cand
    raise DynslamError(f"configs folder with base.yaml not found: looked in {cands[0]} and {cands[1]}")


def preset_names() -> list[str]:
    """Names of the presets in ``configs/presets/``."""
    folder = configs_dir() / "presets"
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []


def preset_path(preset: str | Path) -> Path:
    """The file of preset ``preset``: a name from ``configs/presets/`` or a path to a YAML file."""
    text = str(preset)
    named = configs_dir() / "presets" / f"{text}.yaml"
    if named.is_file():
        return named
    path = Path(text)
    if path.suffix in (".yaml", ".yml") or path.parent != Path("."):
        if not path.is_file():
            raise DynslamError(f"preset file not found: {path}")
        return path
    raise DynslamError(f"unknown preset '{text}'; presets: {', '.join(preset_names()) or 'none'} (or a YAML file path)")


def _read_yaml(path: Path) -> dict:
    if not path.is_file():
        raise DynslamError(f"config file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        raise DynslamError(f"invalid YAML in {path}{where}: {getattr(exc, 'problem', exc)}") from None
    if not isinstance(data, dict):
        raise DynslamError(f"config file {path} must hold a mapping of sections, got {type(data).__name__}")
    return data


def _field_types(cls) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


# numbers YAML 1.1 leaves as strings: exponents without a dot (1e-8, 5E+3)
_FLOAT_TEXT = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")


def _coerce(value: Any, tp: Any, key: str, source: str) -> Any:
    """Check/convert a YAML value to the field's annotated type."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, key, source)
            except DynslamError as exc:
                errors.append(str(exc))
        raise DynslamError(errors[0] if errors else f"bad value for {key} in {source}")
    if tp is Any:
        return value
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise DynslamError(f"config key '{key}' in {source} must be true/false, got {value!r}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise DynslamError(f"config key '{key}' in {source} must be an integer, got {value!r}")
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str) and _FLOAT_TEXT.fullmatch(value.strip()):
            return float(value)  # PyYAML (YAML 1.1) reads 1e-8 without a dot as a string
        raise DynslamError(f"config key '{key}' in {source} must be a number, got {value!r}")
    if tp is str:
        if isinstance(value, str):
            return value
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return str(value)
        raise DynslamError(f"config key '{key}' in {source} must be a string, got {value!r}")
    if tp is list or origin is list:
        if isinstance(value, (list, tuple)):
            return list(value)
        raise DynslamError(f"config key '{key}' in {source} must be a list, got {value!r}")
    if tp is dict or origin is dict:
        if isinstance(value, dict):
            return dict(value)
        raise DynslamError(f"config key '{key}' in {source} must be a mapping, got {value!r}")
    return value


def _merge_into(obj: Any, data: dict, source: str, prefix: str = "") -> None:
    """Set the fields of dataclass ``obj`` from ``data``, recursing into nested dataclasses."""
    types_ = _field_types(type(obj))
    for key, value in data.items():
        full = f"{prefix}{key}"
        if key not in types_:
            valid = ", ".join(sorted(types_))
            where = f"section '{prefix[:-1]}'" if prefix else "the top level"
            raise DynslamError(f"unknown config key '{full}' in {source}; valid keys in {where}: {valid}")
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise DynslamError(f"config key '{full}' in {source} must be a mapping of its keys")
            _merge_into(current, value, source, prefix=f"{full}.")
        else:
            setattr(obj, key, _coerce(value, types_[key], full, source))


def _sequence_sections(data: dict, seq_name: Optional[str], source: str) -> list[dict]:
    seqs = data.pop("sequences", None) or {}
    if not isinstance(seqs, dict):
        raise DynslamError(f"'sequences' in {source} must map sequence-name patterns to config sections")
    if not seq_name:
        return []
    return [sec for pat, sec in seqs.items() if fnmatch.fnmatch(seq_name, str(pat))]


def parse_override(text: str) -> tuple[list[str], Any]:
    if "=" not in text:
        raise DynslamError(f"override '{text}' must look like section.key=value")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key or any(not part for part in key.split(".")):
        raise DynslamError(f"override '{text}' has an empty key")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    return key.split("."), value


def apply_overrides(cfg: Config, overrides: Iterable[str]) -> Config:
    for text in overrides:
        path, value = parse_override(text)
        nested: Any = value
        for part in reversed(path):
            nested = {part: nested}
        _merge_into(cfg, nested, f"--set {text}")
    return cfg


def load_config(
    dataset: Optional[str] = None,
    sequence: Optional[str] = None,
    config_file: Optional[str | Path] = None,
    overrides: Iterable[str] = (),
    preset: Optional[str | Path] = None,
) -> Config:
    """Resolve the configuration for a sequence of ``dataset`` (tum/bonn/synth) named ``sequence``,
    with the preset named ``preset`` (or its file) layered after the dataset file."""
    ppath = preset_path(preset) if preset else None
    cfg = Config()
    cdir = configs_dir()
    layers: list[tuple[str, dict]] = []
    base = cdir / "base.yaml"
    base_data = _read_yaml(base)
    layers.append((str(base), base_data))
    if dataset in DATASET_FILES and (cdir / DATASET_FILES[dataset]).is_file():
        dpath = cdir / DATASET_FILES[dataset]
        ddata = _read_yaml(dpath)
        per_seq = _sequence_sections(ddata, sequence, str(dpath))
        layers.append((str(dpath), ddata))
        layers.extend((f"{dpath} (sequences)", sec or {}) for sec in per_seq)
    for cpath in [p for p in (ppath, config_file) if p is not None]:
        cpath = Path(cpath)
        cdata = _read_yaml(cpath)
        per_seq = _sequence_sections(cdata, sequence, str(cpath))
        layers.append((str(cpath), cdata))
        layers.extend((f"{cpath} (sequences)", sec or {}) for sec in per_seq)
    for source, data in layers:
        data = dict(data)
        data.pop("sequences", None)
        _merge_into(cfg, data, source)
    return validate_config(apply_overrides(cfg, overrides))


def validate_config(cfg: Any, prefix: str = "") -> Any:
    """Check every value against its field's rule, then each dataclass's cross-field rules;
    the first violation is a one-line DynslamError naming the key. Returns ``cfg``."""
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            validate_config(value, f"{prefix}{f.name}.")
            continue
        rule = rule_of(f)
        problem = rule.violation(value) if rule is not None else None
        if problem:
            raise DynslamError(f"config: {prefix}{f.name} {problem}")
    validate = getattr(cfg, "validate", None)
    if validate is not None:
        for problem in validate(lambda name: f"{prefix}{name}"):
            raise DynslamError(f"config: {problem}")
    return cfg


def config_to_dict(cfg: Any) -> dict:
    return dataclasses.asdict(cfg)


def config_to_yaml(cfg: Any, comments: bool = True) -> str:
    """YAML of a config; with ``comments`` each key is preceded by its help text."""
    if not comments:
        return yaml.safe_dump(config_to_dict(cfg), sort_keys=False)
    lines: list[str] = []

    def emit(obj: Any, indent: int) -> None:
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            help_text = f.metadata.get("help", "")
            pad = "  " * indent
            if help_text:
                lines.append(f"{pad}# {help_text}")
            if dataclasses.is_dataclass(value):
                lines.append(f"{pad}{f.name}:")
                emit(value, indent + 1)
            else:
                dumped = yaml.safe_dump({f.name: value}, default_flow_style=True, width=10**6).strip()
                if dumped.startswith("{") and dumped.endswith("}"):
                    dumped = dumped[1:-1]
                lines.append(f"{pad}{dumped}")

    emit(cfg, 0)
    return "\n".join(lines) + "\n"


def save_config(cfg: Any, path: str | Path) -> Path:
    return write_text_atomic(path, config_to_yaml(cfg))


def config_from_file(path: str | Path) -> Config:
    """Load a saved (resolved) config.yaml without the base/dataset layers."""
    cfg = Config()
    _merge_into(cfg, _read_yaml(Path(path)), str(path))
    return validate_config(cfg)
