"""config/resolve.py: config resolution shared by the library and the CLI."""

from __future__ import annotations

import subprocess
import sys

import pytest

from dynslam_cli.config.resolve import cut_overrides, resolve_config
from dynslam_cli.errors import DynslamError


def test_cut_options_become_overrides():
    assert cut_overrides() == []
    assert cut_overrides("/d", 10, 5, 2) == ["data.root=/d", "data.frames=10", "data.start=5", "data.stride=2"]
    cfg = resolve_config("bonn/crowd", None, ["run.seed=3"], data_root="/tmp/x", frames=12, start=4, stride=3)
    assert (cfg.data.frames, cfg.data.start, cfg.data.stride, cfg.data.root, cfg.run.seed) == (12, 4, 3, "/tmp/x", 3)
    # a cut option wins over the same key given with --set
    assert resolve_config("bonn/crowd", None, ["data.frames=7"], frames=9).data.frames == 9
    assert resolve_config("bonn/crowd", None, ["data.frames=7"]).data.frames == 7


def test_dataset_file_and_config_file_layers(tmp_path):
    from dynslam_cli.config import load_config

    bonn, tum = resolve_config("bonn/crowd"), resolve_config("tum/fr3_walking_xyz")
    assert bonn == load_config("bonn", "crowd") and tum == load_config("tum", "fr3_walking_xyz")
    f = tmp_path / "c.yaml"
    f.write_text("run:\n  seed: 41\n")
    assert resolve_config("bonn/crowd", f).run.seed == 41
    assert resolve_config("bonn/crowd", str(f), ["run.seed=2"]).run.seed == 2
    with pytest.raises(DynslamError, match="no_such_key"):
        resolve_config("bonn/crowd", None, ["run.no_such_key=1"])
    with pytest.raises(DynslamError, match="config file not found"):
        resolve_config("bonn/crowd", tmp_path / "missing.yaml")


def test_cli_helper_is_the_library_function():
    from dynslam_cli.commands import _common

    assert _common.resolve_config is resolve_config


def test_eval_library_does_not_import_the_cli_layer():
    code = ("import sys; import dynslam_cli.eval.ablate as ab, dynslam_cli.eval.tables, dynslam_cli.eval.ate; "
            "cells = ab.build_grid(['bonn/crowd'], ['dynamic'], [], [], [], [], ['0']); "
            "ab.key_cells(cells, None, None, 5); "
            "print(sorted(m for m in sys.modules if m.startswith('dynslam_cli.commands') or m == 'typer'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
