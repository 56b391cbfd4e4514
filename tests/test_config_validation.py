"""Config values are checked at load time, before any work: every numeric key has a rule declared
in its dataclass field, closed string sets have choices, cross-field rules live in ``validate``;
a violation is one line naming the key, the rule and the value."""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from dynslam_cli.cli import app
from dynslam_cli.config import Config, load_config
from dynslam_cli.config.fields import Rule, opt, rule_of
from dynslam_cli.config.loader import DATASET_FILES, config_from_file, configs_dir, validate_config
from dynslam_cli.errors import DynslamError

CLOSED_STRINGS = {"motion.segmenter", "motion.encoder", "motion.encoder_pooling", "eval.align", "run.mode",
                  "run.device"}


def _leaves(obj=None, prefix=""):
    obj = Config() if obj is None else obj
    hints = typing.get_type_hints(type(obj))
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            yield from _leaves(value, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", f, hints[f.name]


def test_every_numeric_key_has_a_rule_and_closed_strings_have_choices():
    numeric = [k for k, f, tp in _leaves() if tp in (int, float)]
    assert len(numeric) > 50
    assert [k for k, f, tp in _leaves() if tp in (int, float) and rule_of(f) is None] == []
    with_choices = {k for k, f, tp in _leaves() if rule_of(f) is not None and rule_of(f).choices is not None}
    assert with_choices == CLOSED_STRINGS
    for key, f, _ in _leaves():  # every default follows its own rule
        rule = rule_of(f)
        assert rule is None or rule.violation(f.default if f.default is not dataclasses.MISSING else None) is None, key
    validate_config(Config())


def test_every_shipped_config_and_sequence_section_is_valid():
    cdir = configs_dir()
    n = 0
    for ds, name in DATASET_FILES.items():
        data = yaml.safe_load((cdir / name).read_text())
        for pattern in [None, *(data.get("sequences") or {})]:
            load_config(ds, None if pattern is None else str(pattern).replace("*", "x").replace("?", "x"))
            n += 1
    for preset in sorted((cdir / "presets").glob("*.yaml")):
        for ds in DATASET_FILES:
            load_config(ds, "crowd", preset=preset.stem)
            n += 1
    assert n >= 15


@pytest.mark.parametrize("override, message", [
    # the faults found by a user
    (["mapping.keyframe_every=0"], "config: mapping.keyframe_every must be >= 1 (got 0)"),
    (["map.near=2.0", "map.far=1.5"], "config: map.near must be < map.far (got 2 >= 1.5)"),
    (["map.hidden_dim=0"], "config: map.hidden_dim must be >= 1 (got 0)"),
    (["run.mesh_resolution=0"], "config: run.mesh_resolution must be > 0 (got 0.0)"),
    (["run.threads=-3"], "config: run.threads must be >= 0 (got -3)"),
    # ranges, open bounds, sentinels, non-finite numbers, choices and checks
    (["synth.depth_holes=1"], "config: synth.depth_holes must be in [0, 1) (got 1.0)"),
    (["mapping.keyframe_ray_fraction=0"], "config: mapping.keyframe_ray_fraction must be in (0, 1] (got 0.0)"),
    (["mapping.lr_pose=-0.5"], "config: mapping.lr_pose must be >= 0 (got -0.5)"),
    (["map.truncation=.nan"], "config: map.truncation must be > 0 (got nan)"),
    (["map.w_sdf=.inf"], "config: map.w_sdf must be >= 0 (got inf)"),
    (["run.device=gpu"], "config: run.device must be one of auto, cpu, cuda (got 'gpu')"),
    (["motion.encoder=resnet"], "config: motion.encoder must be one of effnet-lite0, onnx, clip, dino, blip, color-hist"),
    (["run.still_seconds=-1"], "config: run.still_seconds must be >= 0 (got -1.0)"),
    (["synth.width=4"], "config: synth.width must be in [8, 4096] (got 4)"),
    # cross-field and list rules
    (["data.intrinsics=[500, 0, 320, 240]"], "config: data.intrinsics must be null or 4 numbers fx, fy, cx, cy"),
    (["data.distortion=[0.1, 0.2]"], "config: data.distortion must be null or 4, 5, 8, 12 or 14 numbers"),
    (["map.bounds=[[0,0,0],[1,0,1]]"], "config: map.bounds must have each minimum < its maximum"),
    (["map.bounds=[0,0,0,1,1,1]"], "config: map.bounds must be null or [[xmin,ymin,zmin],[xmax,ymax,zmax]]"),
    (["motion.encoder_std=[0.2, 0, 0.2]"], "config: motion.encoder_std must be empty or 3 numbers"),
    (["motion.prior_classes=[person, 3]"], "config: motion.prior_classes must be a list of class names"),
])
def test_invalid_values_are_one_line_errors(override, message):
    with pytest.raises(DynslamError) as info:
        load_config("tum", "fr3_walking_xyz", overrides=override)
    msg = str(info.value)
    assert msg.startswith(message) and "\n" not in msg, msg


def test_sentinels_and_boundaries_pass():
    cfg = load_config(overrides=["mapping.lr_pose=0", "run.threads=0", "run.threads=4", "synth.depth_holes=0",
                                 "mapping.keyframe_ray_fraction=1", "run.still_seconds=0", "map.near=0"])
    assert cfg.mapping.lr_pose == 0 and cfg.run.threads == 4 and cfg.map.near == 0


def test_a_config_file_layer_and_a_saved_config_are_checked(tmp_path: Path):
    f = tmp_path / "c.yaml"
    f.write_text("map:\n  near: 6.0\n")
    with pytest.raises(DynslamError, match=r"config: map\.near must be < map\.far \(got 6 >= 5\)"):
        load_config(config_file=f)
    # a later layer can repair what an earlier one broke: the check runs once, after all layers
    assert load_config(config_file=f, overrides=["map.far=7"]).map.far == 7.0
    saved = tmp_path / "config.yaml"
    saved.write_text("mapping:\n  every: 0\n")
    with pytest.raises(DynslamError, match=r"config: mapping\.every must be >= 1 \(got 0\)"):
        config_from_file(saved)


def test_rule_descriptions():
    assert Rule(min=0).describe() == ">= 0" and Rule(above=0).describe() == "> 0"
    assert Rule(min=0, below=1).describe() == "in [0, 1)" and Rule(above=0, max=1).describe() == "in (0, 1]"
    assert Rule(max=5).describe() == "<= 5" and Rule(below=0.5).describe() == "< 0.5"
    assert Rule(min=0, also=(-1,)).describe() == ">= 0 or -1"
    assert Rule(check=(lambda v: v % 2 == 1, "odd")).describe() == "odd"
    assert Rule(check=(lambda v: v % 2 == 1, "odd")).violation(4) == "must be odd (got 4)"
    assert Rule(choices=("a", "b")).violation("c") == "must be one of a, b (got 'c')"
    assert Rule(min=0).violation(True) is None  # booleans are not numbers here (typed fields reject them)
    assert rule_of(opt(1, "h", min=1)) == Rule(min=1) and rule_of(opt(1, "h")) is None
    assert opt([1], "h", min=0).default_factory() == [1]


@pytest.mark.parametrize("args, message", [
    (["config", "show", "--set", "map.near=2", "--set", "map.far=1.5"], "error: config: map.near must be < map.far"),
    (["config", "show", "--set", "run.threads=-3"], "error: config: run.threads must be >= 0 (got -3)"),
])
def test_cli_config_errors(args, message):
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2 and "Traceback" not in res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(message), res.output


def test_cli_run_refuses_before_any_work(tmp_path: Path):
    from dynslam_cli.slam.toyscene import write_sequence

    seq = write_sequence(tmp_path / "toy", n=2, width=32, height=24)
    before = sorted(p.name for p in tmp_path.rglob("*"))
    out = tmp_path / "run"
    for bad in ("mapping.keyframe_every=0", "map.hidden_dim=0", "run.mesh_resolution=0"):
        res = CliRunner().invoke(app, ["run", "--seq", str(seq), "--mode", "static", "--out", str(out), "-q",
                                       "--set", bad])
        assert res.exit_code == 2 and "Traceback" not in res.output, res.output
        lines = [ln for ln in res.output.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith(f"error: config: {bad.split('=')[0]} must be"), res.output
    assert not out.exists() and sorted(p.name for p in tmp_path.rglob("*")) == before


def test_cli_synth_size_and_seed_follow_the_config_rules(tmp_path: Path):
    out = tmp_path / "scene"
    for args, message in ((["--size", "4x4"], "error: config: synth.width must be in [8, 4096] (got 4)"),
                          (["--seed", "-1"], "error: config: synth.seed must be >= 0 (got -1)")):
        res = CliRunner().invoke(app, ["synth", "static", "--out", str(out), "-q"] + args)
        assert res.exit_code == 2 and "Traceback" not in res.output
        assert res.output.strip() == message, res.output
    assert list(tmp_path.iterdir()) == []
