from pathlib import Path

import pytest
import yaml

from dynslam_cli.config import Config, apply_overrides, config_to_yaml, load_config
from dynslam_cli.config.loader import config_from_file
from dynslam_cli.errors import DynslamError


def test_defaults_and_base_yaml_load():
    cfg = load_config()
    assert isinstance(cfg, Config)
    assert cfg.tracking.n_rays == 1024
    assert cfg.mapping.n_rays == 2048
    assert cfg.map.truncation == pytest.approx(0.10)


def test_dataset_and_sequence_layers():
    fr3 = load_config("tum", "fr3_walking_xyz")
    assert fr3.data.intrinsics == [535.4, 539.2, 320.1, 247.6]
    fr1 = load_config("tum", "fr1_desk")
    assert fr1.data.intrinsics[0] == pytest.approx(517.3)
    assert fr1.data.distortion[0] == pytest.approx(0.2624)
    bonn = load_config("bonn", "crowd")
    assert bonn.data.intrinsics[0] == pytest.approx(542.822841)


def test_overrides_types_and_precedence(tmp_path: Path):
    f = tmp_path / "c.yaml"
    f.write_text("tracking:\n  iters: 20\nmap:\n  bounds: [[0,0,0],[1,1,1]]\n")
    cfg = load_config("tum", "fr3_walking_xyz", f, ["tracking.iters=7", "run.mode=static", "map.truncation=1"])
    assert cfg.tracking.iters == 7
    assert cfg.run.mode == "static"
    assert cfg.map.truncation == 1.0 and isinstance(cfg.map.truncation, float)
    assert cfg.map.bounds == [[0, 0, 0], [1, 1, 1]]


@pytest.mark.parametrize("override, fragment", [
    ("map.nonsense=1", "unknown config key 'map.nonsense'"),
    ("nosection.x=1", "unknown config key 'nosection'"),
    ("tracking.iters=abc", "must be an integer"),
    ("run.save_masks=3", "must be true/false"),
    ("map.w_depth=1e-8x", "must be a number"),
    ("map.w_depth=e-8", "must be a number"),
    ("tracking", "section.key=value"),
])
def test_bad_overrides(override, fragment):
    with pytest.raises(DynslamError, match=fragment.replace("(", r"\(").replace(".", r"\.")):
        apply_overrides(Config(), [override])


def test_exponent_without_a_dot_is_a_number(tmp_path: Path):
    # PyYAML (YAML 1.1) reads 1e-8 as a string; float fields accept it from --set and from files
    f = tmp_path / "c.yaml"
    f.write_text("map:\n  w_sdf: 5E+3\n")
    cfg = load_config(config_file=f, overrides=["map.w_depth=1e-8", "map.w_rgb=2.5e1"])
    assert cfg.map.w_sdf == 5000.0 and cfg.map.w_depth == 1e-8 and cfg.map.w_rgb == 25.0
    with pytest.raises(DynslamError, match="must be an integer"):
        apply_overrides(Config(), ["tracking.iters=1e3"])


def test_unknown_key_in_file_names_file_and_valid_keys(tmp_path: Path):
    f = tmp_path / "bad.yaml"
    f.write_text("mapping:\n  iterz: 3\n")
    with pytest.raises(DynslamError) as info:
        load_config(config_file=f)
    msg = str(info.value)
    assert "mapping.iterz" in msg and str(f) in msg and "iters" in msg


def test_yaml_round_trip(tmp_path: Path):
    cfg = load_config("bonn", "crowd", overrides=["tracking.iters=13"])
    text = config_to_yaml(cfg)
    assert "# Adam iterations per frame" in text
    p = tmp_path / "config.yaml"
    p.write_text(text)
    assert yaml.safe_load(text)["tracking"]["iters"] == 13
    assert config_from_file(p) == cfg


def test_cli_config_show_and_error():
    from typer.testing import CliRunner

    from dynslam_cli.cli import app

    r = CliRunner().invoke(app, ["config", "show", "--seq", "bonn/crowd", "--plain"])
    assert r.exit_code == 0, r.output
    assert yaml.safe_load(r.output)["data"]["intrinsics"][0] == pytest.approx(542.822841)
    r = CliRunner().invoke(app, ["config", "show", "--set", "map.bogus=1"])
    assert r.exit_code == 2
    assert "unknown config key 'map.bogus'" in r.output
    assert "Traceback" not in r.output


def test_yolo_person_preset_loads_over_bonn():
    cfg = load_config("bonn", "crowd", preset="yolo-person")
    assert cfg.motion.segmenter == "yolo-seg" and cfg.motion.prior_classes == ["person"]
    assert cfg.data.max_depth == 3.178  # bonn.yaml beneath it
    # the same algorithm as the defaults otherwise
    plain = load_config("bonn", "crowd")
    assert (cfg.tracking, cfg.mapping, cfg.run) == (plain.tracking, plain.mapping, plain.run)


def test_presets_load_and_differ_where_they_should():
    from dynslam_cli.config.loader import preset_names

    assert {"coslam", "paper", "yolo-person"} <= set(preset_names())
    base = load_config("synth", "walker")
    coslam = load_config("synth", "walker", preset="coslam")
    paper = load_config("synth", "walker", preset="paper")
    assert base.tracking.backend and not coslam.tracking.backend and not paper.tracking.backend
    assert coslam.tracking.icp_init and paper.tracking.icp_init and coslam.mapping.lr_pose > 0
    assert (coslam.run.mode, paper.run.mode, base.run.mode) == ("static", "dynamic", "dynamic")
    assert paper.run.still_seconds == 0 and paper.run.forget_radius == 0 and base.run.still_seconds == 0.67
    assert coslam.map == base.map and coslam.motion == base.motion
    # a preset sits between the dataset file and --config / --set
    f = Path(__file__).parent / "_preset_probe.yaml"
    cfg = load_config("synth", "walker", preset="coslam", overrides=["run.mode=dynamic"])
    assert cfg.run.mode == "dynamic" and not cfg.tracking.backend and not f.exists()


def test_preset_by_path_and_unknown_preset(tmp_path: Path):
    f = tmp_path / "mine.yaml"
    f.write_text("tracking:\n  iters: 3\n")
    assert load_config(preset=str(f)).tracking.iters == 3
    with pytest.raises(DynslamError, match=r"unknown preset 'nope'; presets: coslam, paper, yolo-person"):
        load_config(preset="nope")
    with pytest.raises(DynslamError, match="preset file not found"):
        load_config(preset=str(tmp_path / "absent.yaml"))


def test_cli_preset_show_and_unknown_preset_error(tmp_path: Path):
    from typer.testing import CliRunner

    from dynslam_cli.cli import app

    r = CliRunner().invoke(app, ["config", "show", "--preset", "coslam", "--plain"])
    assert r.exit_code == 0, r.output
    shown = yaml.safe_load(r.output)
    assert shown["tracking"]["backend"] is False and shown["run"]["mode"] == "static"
    out = tmp_path / "run"
    for cmd in (["config", "show"], ["run", "--seq", "synth/walker", "--out", str(out)],
                ["ablate", "--seq", "synth/walker", "--dry-run", "--results", str(tmp_path / "abl")]):
        r = CliRunner().invoke(app, cmd + ["--preset", "nope"])
        assert r.exit_code == 2, (cmd, r.output)
        assert r.output.strip().splitlines()[-1].startswith("error: unknown preset 'nope'; presets: coslam, paper")
        assert "Traceback" not in r.output
    assert not out.exists() and not (tmp_path / "abl").exists()


def _leaves(d, pre=""):
    for k, v in (d or {}).items():
        if isinstance(v, dict) and k != "sequences":
            yield from _leaves(v, f"{pre}{k}.")
        else:
            yield f"{pre}{k}"


def test_dataset_files_hold_sensor_and_data_facts_only():
    # the check ../shared/tools/structure.py makes: data.*, map.bounds and synth.* only
    root = Path(__file__).resolve().parents[1] / "configs"
    for ds in ("bonn", "tum", "synth"):
        d = yaml.safe_load((root / f"{ds}.yaml").read_text()) or {}
        seqs = d.pop("sequences", {}) or {}
        keys = list(_leaves(d)) + [k for s in seqs.values() for k in _leaves(s)]
        algo = [k for k in keys if not (k.startswith("data.") or k == "map.bounds" or k.startswith("synth."))]
        assert keys and not algo, (ds, algo)


def test_the_config_has_under_90_keys():
    keys = list(_leaves(yaml.safe_load(config_to_yaml(Config(), comments=False))))
    assert 50 < len(keys) < 90, len(keys)
