"""`dynslam demo` and run/demo.py: a tiny demo rendered, run, evaluated and reported."""

import json
import math

import pytest
import yaml
from typer.testing import CliRunner

from dynslam_cli.cli import app
from dynslam_cli.errors import DynslamError
from dynslam_cli.run.demo import DEMO_SETS, evaluate_ate, format_report, run_demo

# A tiny scene and map: the whole demo in a few seconds (tests/test_smoke_pipeline.py's settings at
# 160x120, where ORB finds enough keypoints for the keyframe backend to start).
TINY = ["map.n_levels=4", "map.log2_hashmap_size=12", "map.voxel_size=0.1",
        "mapping.first_iters=30", "tracking.iters=3", "tracking.n_rays=128",
        "mapping.iters=3", "mapping.n_rays=256", "tracking.ignore_border=2", "run.mesh_resolution=0.08",
        "motion.encoder=color-hist", "motion.check_width=48", "synth.width=160",
        "synth.height=120", "synth.frames=10", "synth.seed=5"]


@pytest.fixture(autouse=True)
def early_check(monkeypatch):
    """The inconsistency check from frame 2 on (its warm-up is 5 frames): these clips are short."""
    monkeypatch.setattr("dynslam_cli.run.loop.CHECK_WARMUP", 2)
    monkeypatch.setattr("dynslam_cli.eval.mesh.MESH_SAMPLES", 5000)  # a coarse mesh score is enough here


def _sets(extra=()):
    return [a for s in list(TINY) + list(extra) for a in ("--set", s)]


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    root = tmp_path_factory.mktemp("demo")
    lines = []
    res = run_demo("walker", out=root / "run", data_root=root / "data", sets=TINY, threads=1, progress=False,
                   say=lines.append)
    return res, lines, root


def test_run_demo_evaluates_the_run(demo):
    res, lines, root = demo
    assert res.frames == 10 and (res.width, res.height) == (160, 120) and res.rendered
    for v in (res.ate_m, res.still_m, res.mesh_accuracy_m, res.mesh_completion_m, res.fps, res.wall_s):
        assert math.isfinite(v) and v >= 0
    assert res.still_m > 0 and res.mask_iou is not None and 0 <= res.mask_iou <= 1
    assert 0 <= res.mesh_completion_ratio <= 1 and res.mask_frames_moving > 0
    assert res.wall_s >= res.render_s + res.run_s + res.eval_s - 1e-6
    assert lines[0] == f"rendering synth/walker (10 frames, 160x120) into {res.scene_dir} ..."
    # the numbers come from the eval files written into the run folder
    ate = json.loads((res.out_dir / "ate.json").read_text())
    assert ate["rmse_m"] == pytest.approx(res.ate_m) and ate["rmse_still_m"] == pytest.approx(res.still_m)
    assert json.loads((res.out_dir / "mask_metrics.json").read_text())["mean_iou_moving"] == pytest.approx(res.mask_iou)
    assert json.loads((res.out_dir / "mesh_metrics.json").read_text())["accuracy_m"] == pytest.approx(res.mesh_accuracy_m)
    saved = json.loads((res.out_dir / "demo_report.json").read_text())
    assert saved["ate_m"] == pytest.approx(res.ate_m) and saved["frames"] == 10
    assert "ATE RMSE" in (res.out_dir / "report.md").read_text()


def test_report_has_the_numbers_and_next_commands(demo):
    res = demo[0]
    text = format_report(res)
    assert f"still camera {100 * res.still_m:.1f} cm; se3 alignment" in text
    assert f"IoU {res.mask_iou:.3f}" in text and "accuracy" in text and "completion" in text
    assert f"{res.fps:.2f} fps" in text and str(res.out_dir) in text
    assert f"dynslam view {res.out_dir}" in text
    assert "dynslam download bonn/crowd && dynslam run --seq bonn/crowd" in text
    ablate = [ln for ln in text.splitlines() if "dynslam ablate" in ln][0]
    assert "--set synth.frames=10" in ablate and f"--data-root {res.data_root}" in ablate
    assert text in (res.out_dir / "report.md").read_text()


def test_cli_threads_and_set_reach_the_config(demo, tmp_path):
    root = demo[2]
    out = tmp_path / "run"
    args = ["demo", "--out", str(out), "--data-root", str(root / "data"), "--threads", "2", "--seed", "3", "-q"]
    res = CliRunner().invoke(app, args + _sets(["tracking.iters=2"]))
    assert res.exit_code == 0, res.output
    cfg = yaml.safe_load((out / "config.yaml").read_text())
    assert cfg["run"]["threads"] == 2 and cfg["run"]["seed"] == 3
    assert cfg["tracking"]["iters"] == 2 and cfg["run"]["mode"] == "dynamic" and cfg["run"]["save_masks"]
    assert json.loads((out / "run.json").read_text())["threads"] == 2
    assert "ATE RMSE" in res.stdout and "next:" in res.stdout and "rendering" not in res.output  # scene cached
    # a folder holding a run is refused without --overwrite, before anything is rendered or run
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    res = CliRunner().invoke(app, args + _sets(["synth.frames=7"]))
    assert res.exit_code == 2
    assert res.output.strip().splitlines() == [
        f"error: run folder {out} already holds a run (run.json says completed, sequence synth/walker); "
        "use --overwrite to replace it (deletes its files) or choose another --out"]
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before
    assert not list((root / "data" / "synth").glob("walker_160x120_7f*"))
    res = CliRunner().invoke(app, args + ["--overwrite"] + _sets(["synth.frames=7"]))
    assert res.exit_code == 0, res.output
    assert json.loads((out / "demo_report.json").read_text())["frames"] == 7
    assert len(list((out / "masks").glob("*.png"))) == 7  # the earlier run's masks are gone


@pytest.mark.parametrize("kw, msg", [
    (dict(preset="nope"), "unknown synthetic preset 'nope'"),
    (dict(threads=0), "--threads must be >= 1, got 0"),
    (dict(device="tpu"), "run.device must be one of auto, cpu, cuda"),
])
def test_user_errors(tmp_path, kw, msg):
    kw = {"preset": "walker", **kw}
    with pytest.raises(DynslamError, match=msg):
        run_demo(out=tmp_path / "run", data_root=tmp_path / "data", sets=TINY, progress=False, **kw)
    assert not (tmp_path / "run").exists() and not (tmp_path / "data").exists()


def test_demo_settings_are_valid_config():
    from dynslam_cli.run.demo import demo_config

    cfg, overrides = demo_config(sets=["synth.frames=5"])
    assert overrides[:len(DEMO_SETS)] == DEMO_SETS and cfg.synth.frames == 5
    assert cfg.run.threads == 1  # one thread unless --threads (onnxruntime too)
    assert (cfg.synth.width, cfg.synth.height, cfg.run.mode, cfg.run.save_masks) == (640, 480, "dynamic", True)
    assert demo_config(threads=2)[0].run.threads == 2


def test_a_run_lost_throughout_is_scored_origin_aligned(demo, tmp_path):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(demo[0].out_dir, run)
    rows = [ln.split() for ln in (run / "traj_est.txt").read_text().splitlines() if not ln.startswith("#")]
    still = " ".join(rows[0][1:])  # every pose on the first one: se3 alignment is impossible
    (run / "traj_est.txt").write_text("".join(f"{r[0]} {still}\n" for r in rows))
    ate = evaluate_ate(run)
    assert ate.alignment == "origin" and ate.rmse_still_m > 0
    assert ate.rmse_m == pytest.approx(ate.rmse_still_m, rel=1e-6)  # it scores exactly what standing still does
    assert json.loads((run / "ate.json").read_text())["alignment"] == "origin"


def test_second_demo_replaces_its_own_folder(demo, tmp_path):
    root = demo[2]
    args = ["demo", "--data-root", str(root / "data"), "--threads", "1", "-q"]
    args += _sets([f"run.results_root={tmp_path}"])
    for _ in range(2):  # the default folder needs no --overwrite
        res = CliRunner().invoke(app, args)
        assert res.exit_code == 0, res.output
    out = tmp_path / "synth" / "walker" / "dynamic"
    assert json.loads((out / "demo_report.json").read_text())["out_dir"] == str(out)
    assert f"dynslam view {out}" in res.stdout


@pytest.mark.parametrize("args, msg", [
    (["--scene", "nope"], "error: unknown synthetic preset 'nope'"),
    (["--preset", "nope"], "error: unknown preset 'nope'"),
])
def test_cli_scene_and_preset_errors(tmp_path, args, msg):
    from typer.testing import CliRunner

    from dynslam_cli.cli import app

    r = CliRunner().invoke(app, ["demo", "--out", str(tmp_path / "run"), "--data-root", str(tmp_path / "data"),
                                 "-q"] + args)
    assert r.exit_code == 2 and r.output.strip().splitlines()[-1].startswith(msg), r.output
    assert not (tmp_path / "run").exists()
