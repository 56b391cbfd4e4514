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

from dynslam_cli.config.resolve import resolve_config
from dynslam_cli.errors import DynslamError
from dynslam_cli.eval import ablate as ab

HERE = Path(__file__).resolve().parent


def fake_runner(spec, cfg, out_dir, resume=False, overwrite=False, progress=False):
    """Writes a run folder like the real runner: GT + noise (std grows without replay) on the first
    data.frames poses; seed 13 fails.  Each call appends its keyword arguments to calls.log."""
    from dynslam_cli.config import save_config

    out_dir, scene = Path(out_dir), Path(spec)
    with open(out_dir / "calls.log", "a") as fh:
        fh.write(json.dumps({"resume": resume, "overwrite": overwrite}) + "\n")
    if cfg.run.seed == 13:
        raise RuntimeError("simulated crash in the runner")
    gt = np.loadtxt(scene / "groundtruth.txt")
    if cfg.data.frames > 0:
        gt = gt[:cfg.data.frames]
    rng = np.random.default_rng(cfg.run.seed)
    sigma = 0.01 if cfg.motion.replay else 0.05
    est = gt.copy()
    est[:, 1:4] += sigma * rng.standard_normal((len(gt), 3))
    np.savetxt(out_dir / "traj_est.txt", est, fmt="%.9f")
    save_config(cfg, out_dir / "config.yaml")
    (out_dir / "run.json").write_text(json.dumps({
        "status": "completed", "mode": cfg.run.mode, "seed": cfg.run.seed, "frames": len(gt),
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


def calls(cell_dir: Path) -> list:
    p = Path(cell_dir) / "calls.log"
    return [json.loads(ln) for ln in p.read_text().splitlines()] if p.is_file() else []


def by_slug(cells) -> dict:
    """{slug: outcome}: ids are the slug plus '__' and the key's hash."""
    out = {}
    for c in cells:
        slug, _, digest = c.id.rpartition("__")
        assert len(digest) == ab.KEY_DIGITS and int(digest, 16) >= 0
        out[slug] = c
    return out


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


def test_cell_keys(scene):
    def keyed(frames=None, extra=(), seeds=("0",)):
        cells = ab.build_grid([str(scene)], ["dynamic"], [], [], ["on"], [], list(seeds), extra=list(extra))
        return ab.key_cells(cells, frames=frames)

    base = keyed()[0]
    assert base.id == f"{base.slug}__{base.key[:ab.KEY_DIGITS]}" and base.slug.endswith("replay-on__seed0")
    assert keyed()[0].key == base.key  # the same options, the same key
    assert keyed(frames=10)[0].key != base.key  # the frame cut
    assert keyed(extra=["tracking.iters=4"])[0].key != base.key  # any --set that changes the config
    assert keyed(seeds=("1",))[0].key != base.key
    # what only changes how a run is carried out is not part of the key
    assert keyed(extra=["run.threads=3", "run.checkpoint_every=7"])[0].key == base.key
    # a --set restating a default is the same config, so the same cell
    assert keyed(extra=["motion.replay=true"])[0].key == base.key
    mat = ab.cell_key_material(str(scene), resolve_config(str(scene)))
    assert mat["sequence"] == str(scene.resolve()) and "threads" not in mat["config"]["run"]


def test_local_run_skip_and_failing_cell(tmp_path, scene):
    cells = ab.build_grid([str(scene)], ["dynamic"], [], [], ["on", "off"], [], ["0", "13"])
    res = ab.ablate(cells, "t1", tmp_path / "abl", runner=fake_runner)
    by = by_slug(res.cells)
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
    st = {slug: c.status for slug, c in by_slug(res2.cells).items()}
    assert st["synth-synth_scene__dynamic__replay-on__seed0"] == "skipped"
    assert len(calls(ok.out_dir)) == 1 and len(calls(bad.out_dir)) == 2


def test_rerun_with_other_frames_makes_new_cells(tmp_path, scene):
    """Fault 4: a rerun with the same --name but other --frames / --set must not report the old cells."""
    cells = ab.build_grid([str(scene)], ["dynamic"], [], [], ["on"], [], ["0", "1"])
    first = ab.ablate(cells, "g", tmp_path / "abl", runner=fake_runner, frames=10)
    assert sorted(c.status for c in first.cells) == ["completed"] * 2
    old_summary = {ext: (tmp_path / "abl" / "g" / f"summary.{ext}").read_text() for ext in ("md", "csv", "json")}
    old_files = {c.id: (Path(c.out_dir) / "ate.json").read_text() for c in first.cells}
    second = ab.ablate(cells, "g", tmp_path / "abl", runner=fake_runner, frames=20)
    assert sorted(c.status for c in second.cells) == ["completed"] * 2  # run, not skipped
    assert not {c.id for c in first.cells} & {c.id for c in second.cells}
    for c in second.cells:
        assert json.loads((Path(c.out_dir) / "ate.json").read_text())["matched"] == 20
        assert json.loads((Path(c.out_dir) / "run.json").read_text())["frames"] == 20
    for c in first.cells:  # the old cells are left as they were
        assert (Path(c.out_dir) / "ate.json").read_text() == old_files[c.id]
        assert json.loads((Path(c.out_dir) / "ate.json").read_text())["matched"] == 10
    summary = json.loads((tmp_path / "abl" / "g" / "summary.json").read_text())
    assert sorted(o["id"] for o in summary) == sorted(c.id for c in second.cells)  # only this grid's cells
    md = (tmp_path / "abl" / "g" / "summary.md").read_text()
    assert all(c.id in md for c in second.cells) and not any(c.id in md for c in first.cells)
    assert md != old_summary["md"]
    # a --set that changes the config: new cells too
    third = ab.ablate(ab.build_grid([str(scene)], ["dynamic"], [], [], ["on"], [], ["0"], extra=["tracking.iters=4"]),
                      "g", tmp_path / "abl", runner=fake_runner, frames=20)
    assert [c.status for c in third.cells] == ["completed"]
    assert third.cells[0].id not in {c.id for c in first.cells + second.cells}
    # the same options again: every cell skipped, the runner not called, the same numbers
    again = ab.ablate(cells, "g", tmp_path / "abl", runner=fake_runner, frames=20)
    assert sorted(c.status for c in again.cells) == ["skipped"] * 2
    assert {c.id: c.ate_rmse_m for c in again.cells} == {c.id: c.ate_rmse_m for c in second.cells}
    assert all(len(calls(c.out_dir)) == 1 for c in again.cells)


def test_failed_and_interrupted_cells_overwrite_or_resume(tmp_path, scene):
    cells = ab.key_cells(ab.build_grid([str(scene)], ["dynamic"], [], [], [], [], ["0", "1"]))
    root = tmp_path / "abl" / "r"
    c_failed, c_interrupted = (root / c.id for c in cells)
    for d, status in ((c_failed, "failed"), (c_interrupted, "interrupted")):
        d.mkdir(parents=True)
        (d / "run.json").write_text(json.dumps({"status": status}))
    (c_interrupted / "checkpoint.pt").write_bytes(b"x")
    for c, d in zip(cells, (c_failed, c_interrupted), strict=True):
        (d / "cell.json").write_text(json.dumps({"cell": c.to_json(), "key": c.key, "status": "failed"}))
    res = ab.ablate(cells, "r", tmp_path / "abl", runner=fake_runner)
    assert sorted(c.status for c in res.cells) == ["completed"] * 2
    assert calls(c_failed) == [{"resume": False, "overwrite": True}]
    assert calls(c_interrupted) == [{"resume": True, "overwrite": False}]
    # a completed run without its key (cell.json of another grid or none) is not taken as done
    (c_failed / "cell.json").unlink()
    (c_failed / "ate.json").unlink()
    ab.ablate(cells, "r", tmp_path / "abl", runner=fake_runner)
    assert calls(c_failed)[-1] == {"resume": False, "overwrite": True} and len(calls(c_failed)) == 2


def test_completed_run_without_ate_is_only_evaluated(tmp_path, scene):
    cells = ab.build_grid([str(scene)], ["dynamic"], [], [], [], [], ["0"])
    res = ab.ablate(cells, "e", tmp_path / "abl", runner=fake_runner)
    d = Path(res.cells[0].out_dir)
    (d / "ate.json").unlink()
    res2 = ab.ablate(cells, "e", tmp_path / "abl", runner=fake_runner)
    assert res2.cells[0].status == "completed" and res2.cells[0].ate_rmse_m == pytest.approx(res.cells[0].ate_rmse_m)
    assert len(calls(d)) == 1  # not run again
    # a wrong-typed ate.json does not break the summary
    (d / "ate.json").write_text(json.dumps({"rmse_m": "abc"}))
    res3 = ab.ablate(cells, "e", tmp_path / "abl", runner=fake_runner)
    assert res3.cells[0].status == "skipped" and res3.cells[0].ate_rmse_m is None


def test_runner_without_overwrite_keyword(tmp_path, scene):
    """Until the runner takes overwrite=, it is called without it."""
    seen = []

    def old_runner(spec, cfg, out_dir, resume=False, progress=True):
        seen.append(resume)
        return fake_runner(spec, cfg, out_dir, resume=resume, progress=progress)

    cells = ab.build_grid([str(scene)], ["dynamic"], [], [], [], [], ["0"])
    assert ab.ablate(cells, "o", tmp_path / "abl", runner=old_runner).cells[0].status == "completed"
    assert seen == [False]


def test_local_executor_two_jobs(tmp_path, scene):
    cells = ab.build_grid([str(scene)], ["dynamic", "static"], [], [], [], [], ["0", "1"])
    res = ab.ablate(cells, "par", tmp_path / "abl", jobs=2, runner=fake_runner)
    assert sorted(c.status for c in res.cells) == ["completed"] * 4
    for c in res.cells:
        assert json.loads((Path(c.out_dir) / "ate.json").read_text())["rmse_m"] == pytest.approx(c.ate_rmse_m)
        cfg_text = (Path(c.out_dir) / "config.yaml").read_text()
        assert f"threads: {max(1, (os.cpu_count() or 1) // 2)}" in cfg_text  # threads divided among jobs
    # an explicit --threads wins; threads are not part of the key, so the finished cells are kept
    res = ab.ablate(cells, "par", tmp_path / "abl", jobs=2, runner=fake_runner, threads=3)
    assert sorted(c.status for c in res.cells) == ["skipped"] * 4
    one = ab.build_grid([str(scene)], ["static"], [], [], [], [], ["5"])
    res = ab.ablate(one, "par", tmp_path / "abl", jobs=2, runner=fake_runner, threads=3)
    assert "threads: 3" in (Path(res.cells[0].out_dir) / "config.yaml").read_text()
    with pytest.raises(DynslamError, match="--threads"):
        ab.ablate(one, "par", tmp_path / "abl", runner=fake_runner, threads=0)


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
    assert all(len(calls(c.out_dir)) == 1 for c in res2.cells)


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
    summary = tmp_path / "abl" / "cli" / "summary.json"
    first_ids = {o["id"] for o in json.loads(summary.read_text())}
    # other --frames: three new cells, nothing skipped, the summary names only them
    res = CliRunner().invoke(app, [*args, "--frames", "12", "--dry-run"])
    assert res.exit_code == 0 and "(done" not in res.output
    res = CliRunner().invoke(app, [*args, "--frames", "12", "--threads", "2"])
    assert res.exit_code == 0, res.output
    assert "3 cells, 0 failed" in res.output and "[skipped]" not in res.output
    new = json.loads(summary.read_text())
    assert len(new) == 3 and not {o["id"] for o in new} & first_ids
    assert all("threads: 2" in (Path(o["out_dir"]) / "config.yaml").read_text() for o in new)
    before = {p: p.read_bytes() for p in (tmp_path / "abl" / "cli").glob("summary.*")}
    for bad, msg in ((["--mode", "sideways"], "error: --mode takes dynamic,static; got 'sideways'"),
                     (["--set", "motion.no_such_key=1"], "no_such_key"),
                     (["--threads", "0"], "error: --threads must be at least 1, got 0")):
        res = CliRunner().invoke(app, [*args, *bad])
        assert res.exit_code == 2 and msg in res.output, res.output
        assert len(res.output.strip().splitlines()) == 1 and "Traceback" not in res.output
        assert {p: p.read_bytes() for p in before} == before  # earlier files unchanged


def test_real_runner_cell(tmp_path):
    """One cell through the real runner on a tiny synthetic scene (skipped until the runner exists)."""
    pytest.importorskip("dynslam_cli.run.runner", reason="dynslam_cli.run.runner not written yet")
    from dynslam_cli.config import load_config
    from dynslam_cli.synth.render import render_preset

    cfg = load_config("synth", "walker").synth
    cfg.width, cfg.height = 64, 48
    scene = tmp_path / "walker"
    render_preset("walker", scene, cfg, frames=10, progress=False)
    tiny = ["map.n_levels=4", "map.log2_hashmap_size=12", "map.voxel_size=0.1",
            "mapping.first_iters=20", "tracking.iters=3", "tracking.n_rays=128",
            "mapping.iters=3", "mapping.n_rays=256", "tracking.ignore_border=2", "run.mesh_resolution=0.1",
            "motion.check_width=32"]
    cells = ab.build_grid([str(scene)], ["dynamic", "static"], ["color-hist"], [], [], [], ["0"], extra=tiny)
    res = ab.ablate(cells, "real", tmp_path / "abl", frames=10)
    assert len(res.cells) == 2
    for cell in res.cells:
        assert cell.status == "completed", cell.error
        assert cell.ate_rmse_m is not None
    assert [c.status for c in ab.ablate(cells, "real", tmp_path / "abl", frames=10).cells] == ["skipped"] * 2
