"""Ablation grids: cell ids, dry run, skip finished cells, failing cell, local pool, Ray, CLI.

The SLAM runner is replaced by ``fake_runner`` (ground truth plus seeded noise) except in the
last test, which uses the real ``dynslam_cli.run.runner`` when it exists.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from dynslam_cli.errors import DynslamError
from dynslam_cli.eval import ablate as ab

HERE = Path(__file__).resolve().parent


def fake_runner(spec, cfg, out_dir, resume=True, progress=False):
    """Writes a run folder like the real runner: GT + noise (std grows without replay); seed 13 fails."""
    from dynslam_cli.config import save_config

    out_dir, scene = Path(out_dir), Path(spec)
    with open(out_dir / "calls.log", "a") as fh:
        fh.write("run\n")
    if cfg.run.seed == 13:
        raise RuntimeError("simulated crash in the runner")
    gt = np.loadtxt(scene / "groundtruth.txt")
    rng = np.random.default_rng(cfg.run.seed)
    sigma = 0.01 if cfg.motion.replay else 0.05
    est = gt.copy()
    est[:, 1:4] += sigma * rng.standard_normal((len(gt), 3))
    np.savetxt(out_dir / "traj_est.txt", est, fmt="%.9f")
    save_config(cfg, out_dir / "config.yaml")
    (out_dir / "run.json").write_text(json.dumps({
        "status": "completed", "mode": cfg.run.mode, "seed": cfg.run.seed,
        "sequence": {"spec": spec, "dataset": "synth", "name": scene.name, "path": str(scene),
                     "groundtruth": str(scene / "groundtruth.txt")}}))
    return SimpleNamespace(status="completed", out_dir=out_dir)


@pytest.fixture()
def scene(tmp_path):
    d = tmp_path / "synth_scene"
    d.mkdir()
    (d / "synth.json").write_text(json.dumps({"intrinsics": [100, 100, 32, 24], "size": [64, 48]}))
    t = 10 + np.arange(40) / 30
    s = np.linspace(0, 3, 40)
    xyz = np.stack([np.cos(s), np.sin(s), 0.1 * s], 1)
    q = np.tile([0, 0, 0, 1.0], (40, 1))
    np.savetxt(d / "groundtruth.txt", np.column_stack([t, xyz, q]), fmt="%.9f")
    return d


def calls(cell_dir: Path) -> int:
    p = cell_dir / "calls.log"
    return len(p.read_text().splitlines()) if p.is_file() else 0


def test_grid_ids_and_overrides(scene):
    cells = ab.build_grid([str(scene)], ["dynamic", "static"], ["effnet-lite0", "color-hist"], [], ["on", "off"],
                          [], ["0", "1"])
    ids = [c.id for c in cells]
    assert len(ids) == 2 * 2 * 2 + 2 == len(set(ids))  # static cells ignore the motion axes
    assert "synth-synth_scene__dynamic__enc-effnet-lite0__replay-on__seed0" in ids
    assert "synth-synth_scene__static__seed1" in ids
    c = next(c for c in cells if c.id.endswith("enc-color-hist__replay-off__seed1"))
    assert {"motion.encoder=color-hist", "motion.replay=false", "run.seed=1", "run.mode=dynamic"} <= set(c.overrides)
    with pytest.raises(DynslamError, match="prior-file"):
        ab.build_grid([str(scene)], ["dynamic"], [], [], [], ["on"], ["0"])
    with pytest.raises(DynslamError, match="on/off"):
        ab.build_grid([str(scene)], ["dynamic"], [], [], ["maybe"], [], ["0"])


def test_local_run_skip_and_failing_cell(tmp_path, scene):
    cells = ab.build_grid([str(scene)], ["dynamic"], [], [], ["on", "off"], [], ["0", "13"])
    res = ab.ablate(cells, "t1", tmp_path / "abl", runner=fake_runner)
    by = {c.id: c for c in res.cells}
    assert len(by) == 4 and res.failed == 2
    ok = by["synth-synth_scene__dynamic__replay-on__seed0"]
    assert ok.status == "completed" and 0.005 < ok.ate_rmse_m < 0.03
    assert by["synth-synth_scene__dynamic__replay-off__seed0"].ate_rmse_m > 2 * ok.ate_rmse_m
    bad = by["synth-synth_scene__dynamic__replay-on__seed13"]
    assert bad.status == "failed" and "simulated crash" in bad.error
    cell_json = json.loads((Path(bad.out_dir) / "cell.json").read_text())
    assert cell_json["status"] == "failed" and "simulated crash" in cell_json["error"]
    summary = (tmp_path / "abl" / "t1" / "summary.md").read_text()
    assert "failed" in summary and f"{ok.ate_rmse_m:.4f}" in summary
    # rerun: finished cells are skipped (the runner is not called again), failed ones retried
    res2 = ab.ablate(cells, "t1", tmp_path / "abl", runner=fake_runner)
    st = {c.id: c.status for c in res2.cells}
    assert st["synth-synth_scene__dynamic__replay-on__seed0"] == "skipped"
    assert calls(Path(ok.out_dir)) == 1 and calls(Path(bad.out_dir)) == 2


def test_local_executor_two_jobs(tmp_path, scene):
    cells = ab.build_grid([str(scene)], ["dynamic", "static"], [], [], [], [], ["0", "1"])
    res = ab.ablate(cells, "par", tmp_path / "abl", jobs=2, runner=fake_runner)
    assert sorted(c.status for c in res.cells) == ["completed"] * 4
    for c in res.cells:
        assert json.loads((Path(c.out_dir) / "ate.json").read_text())["rmse_m"] == pytest.approx(c.ate_rmse_m)
        cfg_text = (Path(c.out_dir) / "config.yaml").read_text()
        assert f"threads: {max(1, (os.cpu_count() or 1) // 2)}" in cfg_text  # threads divided among jobs


def test_ray_executor_and_rerun(tmp_path, scene, monkeypatch):
    pytest.importorskip("ray", reason="ray is not installed (optional extra 'ray')")
    # Ray workers import the fake runner from this folder
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")
    cells = ab.build_grid([str(scene)], ["dynamic"], [], [], ["on", "off"], [], ["0", "1"])
    res = ab.ablate(cells, "ray", tmp_path / "abl", executor="ray", num_cpus=2, runner=fake_runner)
    assert sorted(c.status for c in res.cells) == ["completed"] * 4, [c.error for c in res.cells]
    pids = {json.loads((Path(c.out_dir) / "cell.json").read_text())["pid"] for c in res.cells}
    assert os.getpid() not in pids  # the cells ran in Ray worker processes
    res2 = ab.ablate(cells, "ray", tmp_path / "abl", executor="ray", num_cpus=2, runner=fake_runner)
    assert sorted(c.status for c in res2.cells) == ["skipped"] * 4
    assert all(calls(Path(c.out_dir)) == 1 for c in res2.cells)


def test_ray_missing_is_a_clear_error(tmp_path, scene, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_ray(name, *a, **k):
        if name == "ray" or name.startswith("ray."):
            raise ImportError("no ray")
        return real_import(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    cells = ab.build_grid([str(scene)], ["dynamic"], [], [], [], [], ["0"])
    with pytest.raises(DynslamError, match="pip install"):
        ab.ablate(cells, "x", tmp_path / "abl", executor="ray", runner=fake_runner)


def test_cli_dry_run_and_run(tmp_path, scene, monkeypatch):
    from typer.testing import CliRunner

    from dynslam_cli.cli import app

    args = ["ablate", "--seq", str(scene), "--mode", "dynamic,static", "--replay", "on,off", "--seeds", "0",
            "--name", "cli", "--results", str(tmp_path / "abl")]
    res = CliRunner().invoke(app, [*args, "--dry-run"])
    assert res.exit_code == 0, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 3 and all(ln.startswith("synth-synth_scene__") for ln in lines)
    monkeypatch.setattr(ab, "DEFAULT_RUNNER", "test_ablate:fake_runner")
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "3 cells, 0 failed" in res.output
    res = CliRunner().invoke(app, [*args, "--dry-run"])
    assert res.output.count("(done, skipped)") == 3
    res = CliRunner().invoke(app, ["ablate", "--seq", str(scene), "--mode", "sideways", "--dry-run"])
    assert res.exit_code == 2 and "error:" in res.output
    res = CliRunner().invoke(app, [*args, "--dry-run", "--set", "motion.no_such_key=1"])
    assert res.exit_code == 2 and "no_such_key" in res.output


def test_real_runner_cell(tmp_path):
    """One cell through the real runner on a tiny synthetic scene (skipped until the runner exists)."""
    pytest.importorskip("dynslam_cli.run.runner", reason="dynslam_cli.run.runner not written yet")
    from dynslam_cli.config import load_config
    from dynslam_cli.synth.render import render_preset

    cfg = load_config("synth", "walker").synth
    cfg.width, cfg.height = 64, 48
    scene = tmp_path / "walker"
    render_preset("walker", scene, cfg, frames=10, progress=False)
    tiny = ["map.n_levels=4", "map.log2_hashmap_size=12", "map.base_resolution=8", "map.voxel_size=0.1",
            "mapping.first_iters=20", "mapping.first_rays=256", "tracking.iters=3", "tracking.n_rays=128",
            "mapping.iters=3", "mapping.n_rays=256", "tracking.ignore_border=2", "run.mesh_resolution=0.1",
            "motion.check_width=32", "run.check_warmup=1"]
    cells = ab.build_grid([str(scene)], ["dynamic", "static"], ["color-hist"], [], [], [], ["0"], extra=tiny)
    res = ab.ablate(cells, "real", tmp_path / "abl", frames=10)
    assert len(res.cells) == 2
    for cell in res.cells:
        assert cell.status == "completed", cell.error
        assert cell.ate_rmse_m is not None
    assert [c.status for c in ab.ablate(cells, "real", tmp_path / "abl", frames=10).cells] == ["skipped"] * 2
