"""Typed configuration: dataclasses per part, YAML files in `configs/`, `--set a.b=v` overrides."""

from dynslam_cli.config.loader import (  # noqa: F401
    apply_overrides,
    config_to_dict,
    config_to_yaml,
    configs_dir,
    load_config,
    save_config,
)
from dynslam_cli.config.schema import Config  # noqa: F401
