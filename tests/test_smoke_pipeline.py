"""CI smoke test: a tiny synthetic clip through run → eval-ate → eval-mesh → eval-masks → tables,
all through the command line, in both modes."""

import json

import pytest

from typer.testing import CliRunner

from dynslam_cli.cli import app

TINY = ["--set", "map.n_levels=4", "--set", "map.log2_hashmap_size=12",
        "--set", "map.voxel_size=0.1", "--set", "mapping.first_iters=30",
        "--set", "tracking.iters=3", "--set", "tracking.n_rays=128", "--set", "mapping.iters=3",
        "--set", "mapping.n_rays=256", "--set", "tracking.ignore_border=2", "--set", "run.threads=1",
        "--set", "run.mesh_resolution=0.08", "--set", "motion.encoder=color-hist", "--set", "motion.check_width=48",
        "--set", "synth.width=96", "--set", "synth.height=72",
        "--set", "synth.frames=12", "--set", "synth.seed=5"]


@pytest.fixture(autouse=True)
def early_check(monkeypatch):
    """The inconsistency check from frame 2 on (its warm-up is 5 frames): these clips are short."""
    monkeypatch.setattr("dynslam_cli.run.loop.CHECK_WARMUP", 2)


def _ok(args):
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    return res.output


def test_run_eval_tables_pipeline(tmp_path):
    data, results = tmp_path / "data", tmp_path / "results"
    runs = {}
    for mode in ("dynamic", "static"):
        out = results / "runs" / "synth" / "walker" / mode
        _ok(["run", "--seq", "synth/walker", "--mode", mode, "--data-root", str(data), "--out", str(out),
             "--save-masks", "-q"] + TINY)
        runs[mode] = out
    _ok(["eval-ate", str(runs["dynamic"]), str(runs["static"])])
    _ok(["eval-mesh", str(runs["dynamic"])])
    _ok(["eval-masks", str(runs["dynamic"])])
    ate = json.loads((runs["dynamic"] / "ate.json").read_text())
    assert ate["matched"] == 12 and ate["rmse_m"] >= 0 and ate["rmse_still_m"] > 0
    assert (runs["dynamic"] / "ate.png").stat().st_size > 0
    mesh = json.loads((runs["dynamic"] / "mesh_metrics.json").read_text())
    assert mesh["accuracy_cm"] >= 0 and 0 <= mesh["completion_ratio"] <= 1
    masks = json.loads((runs["dynamic"] / "mask_metrics.json").read_text())
    assert masks["frames"] == 12
    _ok(["tables", "--results", str(results), "--out", str(tmp_path / "tables")])
    table1 = (tmp_path / "tables" / "table1_ate.md").read_text()
    assert "walker" in table1
    for ext in ("csv", "md", "tex"):
        assert (tmp_path / "tables" / f"table1_ate.{ext}").is_file()
