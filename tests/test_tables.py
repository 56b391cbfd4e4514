"""`dynslam tables` on a fake results tree: values propagate from the run files into the tables."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from dynslam_cli.eval.ate import evaluate_run_ate
from dynslam_cli.eval.tables import Cell, stat_cell, make_tables


def _gt(path: Path):
    t = 5 + np.arange(30) / 30
    s = np.linspace(0, 2, 30)
    np.savetxt(path, np.column_stack([t, np.cos(s), np.sin(s), 0.2 * s, np.tile([0, 0, 0, 1.0], (30, 1))]), fmt="%.9f")
    return np.loadtxt(path)


def make_run(root: Path, rel: str, gt_file: Path, seq=("bonn", "crowd"), mode="dynamic", seed=0, sigma=0.02,
             motion=None, updates=None, timing=None, mesh=None, masks=False, data=None, seq_path=None, noise_seed=None):
    """A completed run on the first ``data.frames`` (default all 30) ground-truth poses."""
    d = root / rel
    d.mkdir(parents=True)
    gt = np.loadtxt(gt_file)
    data = data or {}
    start, stride = data.get("start", 0), data.get("stride", 1)
    gt = gt[start::stride][:data.get("frames") or None]
    est = gt.copy()
    est[:, 1:4] += sigma * np.random.default_rng(seed if noise_seed is None else noise_seed).standard_normal((len(gt), 3))
    np.savetxt(d / "traj_est.txt", est, fmt="%.9f")
    sequence = {"dataset": seq[0], "name": seq[1], "groundtruth": str(gt_file)}
    if seq_path is not None:
        sequence["path"] = str(seq_path)
    (d / "run.json").write_text(json.dumps({"status": "completed", "mode": mode, "seed": seed, "frames": len(gt),
                                            "sequence": sequence}))
    import yaml

    (d / "config.yaml").write_text(yaml.safe_dump({"motion": motion or {}, "run": {"mode": mode, "seed": seed},
                                                   "data": {"start": start, "frames": data.get("frames", 0),
                                                            "stride": stride}}))
    if updates is not None:
        (d / "classifier_updates.jsonl").write_text("".join(json.dumps({"frame": f}) + "\n" for f in updates))
    if timing is not None:
        (d / "timing.json").write_text(json.dumps({"frames": 30, "fps": 1000 / sum(timing["mean_ms"].values()),
                                                   **timing}))
    if mesh is not None:
        (d / "mesh_metrics.json").write_text(json.dumps(mesh))
    if masks:
        import cv2

        (d / "masks").mkdir()
        for ts in ("5.000000", "5.500000"):
            cv2.imwrite(str(d / "masks" / f"{ts}.png"), np.zeros((12, 16), np.uint8))
    return evaluate_run_ate(d).rmse_m


def rows(path: Path) -> dict:
    with open(path) as fh:
        return {r["row"]: r for r in csv.DictReader(fh)}


def test_stat_cell_over_seeds():
    assert stat_cell([]) == Cell() and stat_cell([(0, None), (1, float("nan"))]) == Cell()
    assert stat_cell([(0, 0.022)]).text == "0.022 (n=1)"
    # two runs of one seed are no spread: averaged, no ±, both counts printed
    c = stat_cell([(0, 0.020), (0, 0.024)])
    assert c.text == "0.022 (n=1 seed, 2 runs)" and c.value == pytest.approx(0.022)
    # duplicates are averaged per seed first, then mean ± std over the seeds
    c = stat_cell([(0, 0.010), (0, 0.030), (1, 0.040), (2, 0.060)])
    assert c.value == pytest.approx(np.mean([0.02, 0.04, 0.06]))
    assert c.text == f"0.040 ± {np.std([0.02, 0.04, 0.06], ddof=1):.3f} (n=3 seeds, 4 runs)"
    assert stat_cell([(0, 7)], integer=True).text == "7 (n=1)"
    assert stat_cell([(0, 3), (1, 3), (2, 3)], integer=True).text == "3 ± 0 (n=3)"
    assert stat_cell([(0, 3), (1, 4)], integer=True).text == "3.5 ± 0.7 (n=2)"


def test_tables_from_fake_results(tmp_path):
    res = tmp_path / "results"
    gt = tmp_path / "gt.txt"
    _gt(gt)
    scene = tmp_path / "crowd_folder"  # the sequence's folder: its rgb.txt tells the full length (30)
    scene.mkdir()
    (scene / "rgb.txt").write_text("# rgb\n" + "".join(f"{5 + i / 30:.6f} rgb/{i}.png\n" for i in range(30)))
    timing = [{"mean_ms": {"tracking": 100.0 + s, "mapping": 10.0}, "median_ms": {"tracking": 100.0 + s, "mapping": 0.0},
               "calls": {"tracking": 30, "mapping": 6}} for s in (0, 1, 2)]
    dyn = [make_run(res, f"runs/bonn/crowd/dyn{s}", gt, seed=s, sigma=0.01, updates=[3, 10, 20], timing=timing[s],
                    mesh={"accuracy_m": 0.02, "completion_m": 0.03, "completion_ratio": 0.8}, masks=(s == 0),
                    seq_path=scene)
           for s in (0, 1, 2)]
    sta = [make_run(res, f"runs/bonn/crowd/static{s}", gt, mode="static", seed=s, sigma=0.2) for s in (0, 1)]
    # a repeat of static seed 0: averaged with the first before the std over seeds
    sta_rep = make_run(res, "runs/bonn/crowd/static0b", gt, mode="static", seed=0, sigma=0.2, noise_seed=7)
    clip = make_run(res, "ablations/enc/clip0", gt, seed=0, sigma=0.05, motion={"encoder": "clip"})
    noreplay = make_run(res, "ablations/rep/off0", gt, seed=0, sigma=0.03, motion={"replay": False},
                        updates=[1, 2, 3, 4, 5, 6, 7])
    synth = make_run(res, "runs/synth/walker/dyn0", gt, seq=("synth", "walker"), sigma=0.004)
    # two runs (same seed) on the first 20 frames of crowd: a clip row of their own
    part = [make_run(res, f"runs/bonn/crowd/part{i}", gt, seed=0, sigma=0.01, data={"frames": 20}, seq_path=scene,
                     noise_seed=10 + i) for i in (0, 1)]
    strided = make_run(res, "runs/bonn/crowd/strided", gt, seed=0, sigma=0.01, data={"start": 2, "stride": 2})
    # an unfinished run is skipped
    (res / "runs/bonn/crowd/broken").mkdir(parents=True)
    (res / "runs/bonn/crowd/broken/run.json").write_text(json.dumps({"status": "failed"}))

    out = make_tables(res)
    assert out.warnings == [f"skipped: run {res / 'runs/bonn/crowd/broken'} is not completed (run.json status: "
                            "failed); pass --include-incomplete to use it anyway"]
    tdir = res / "tables"
    t1 = rows(tdir / "table1_ate.csv")
    crowd = t1["bonn/crowd"]
    m, sd = np.mean(dyn), np.std(dyn, ddof=1)
    assert crowd["ours dynamic"] == f"{m:.3f} ± {sd:.3f} (n=3)"
    per_seed = [(sta[0] + sta_rep) / 2, sta[1]]
    assert crowd["ours static"] == f"{np.mean(per_seed):.3f} ± {np.std(per_seed, ddof=1):.3f} (n=2 seeds, 3 runs)"
    assert crowd["frames"] == "all (30)"
    assert crowd["paper"] == "0.116" and crowd["ReFusion"] == "0.204" and crowd["Co-SLAM"] == "fail"
    assert crowd["best"] == "ours dynamic"  # ~0.017 beats every published number
    still = json.loads((res / "runs/bonn/crowd/dyn0/ate.json").read_text())["rmse_still_m"]
    assert crowd["still camera"] == f"{still:.3f} ± 0.000 (n=3 seeds, 6 runs)"
    # the clips: rows of their own, marked, without the full-sequence published numbers beside them
    part_row = t1["bonn/crowd [frames 0–19]"]
    assert part_row["frames"] == "20 of 30"
    assert part_row["ours dynamic"] == f"{np.mean(part):.3f} (n=1 seed, 2 runs)"
    assert all(part_row[k] == "—" for k in ("ReFusion", "StaticFusion", "DynaSLAM", "Co-SLAM", "paper"))
    assert part_row["best"] == ""
    strided_row = t1["bonn/crowd [frames 2–28 step 2]"]
    assert strided_row["frames"] == "clip of 14 frames" and strided_row["ours dynamic"] == f"{strided:.3f} (n=1)"
    assert list(t1).index("bonn/crowd") < list(t1).index("bonn/crowd [frames 0–19]")
    assert t1["synth/walker"]["ours dynamic"] == f"{synth:.3f} (n=1)" and t1["synth/walker"]["paper"] == "—"
    assert t1["tum/fr3_walking_xyz"]["ours dynamic"] == "—" and t1["tum/fr3_walking_xyz"]["best"] == "paper"
    assert t1["tum/fr3_walking_xyz"]["frames"] == "—"
    assert t1["tum/fr3_sitting_static"]["best"] == "paper"  # 0.007 < 0.009 (tied ReFusion/DynaSLAM)
    md = (tdir / "table1_ate.md").read_text()
    assert f"**{m:.3f} ± {sd:.3f} (n=3)**" in md and "Palazzolo" in md
    assert "published numbers are on full sequences" in md and "n = seeds" in md
    tex = (tdir / "table1_ate.tex").read_text()
    assert r"\textbf{" in tex and r"bonn/crowd" in tex.replace(r"\_", "_")
    # the ablation tables
    enc_rows = rows(tdir / "ablation_encoder.csv")
    enc = enc_rows["bonn/crowd"]
    assert enc["clip"] == f"{clip:.3f} (n=1)" and enc["effnet-lite0"].startswith(f"{m:.3f}")
    assert enc_rows["bonn/balloon"]["paper BLIP-2"] == "0.206"
    assert enc_rows["bonn/crowd [frames 0–19]"]["paper BLIP-2"] == "—"
    rep = rows(tdir / "ablation_replay.csv")["bonn/crowd"]
    assert rep["updates with replay"] == "3 ± 0 (n=3)" and rep["updates without replay"] == "7 (n=1)"
    assert rep["ATE without replay"] == f"{noreplay:.3f} (n=1)"
    rt = rows(tdir / "runtime.csv")
    crowd_rt = rt["bonn/crowd (dynamic)"]
    assert crowd_rt["tracking /frame"] == "101.0 ± 1.0 (n=3)" and crowd_rt["tracking /call"] == "101.0 ± 1.0 (n=3)"
    # mapping ran on 6 of 30 frames: 10 ms per frame is 50 ms per call
    assert crowd_rt["mapping /frame"] == "10.0 ± 0.0 (n=3)" and crowd_rt["mapping /call"] == "50.0 ± 0.0 (n=3)"
    paper = rt["paper (Bonn, RTX 3090)"]  # per frame; a component we also time shares its column
    assert paper["tracking /frame"] == "149" and paper["tracking /call"] == "—" and paper["classifier_update"] == "397"
    assert "per call" in (tdir / "runtime.md").read_text()
    mesh = rows(tdir / "mesh.csv")["bonn/crowd"]
    assert mesh["accuracy dyn (cm)"] == "2.00 ± 0.00 (n=3)" and mesh["ratio dyn (%)"] == "80.00 ± 0.00 (n=3)"
    assert mesh["accuracy static (cm)"] == "—" and mesh["frames"] == "all (30)"
    # plots
    assert (tdir / "plots" / "classifier_updates_bonn-crowd.png").stat().st_size > 1000
    assert any(p.name.startswith("montage_runs__bonn__crowd__dyn0") for p in out.files)
    assert out.runs == 12
    assert "broken" in (tdir / "README.md").read_text()


def test_runtime_without_calls(tmp_path):
    res = tmp_path / "results"
    gt = tmp_path / "gt.txt"
    _gt(gt)
    make_run(res, "runs/bonn/crowd/a", gt, timing={"mean_ms": {"map": 12.0}, "median_ms": {"map": 0.0}})
    rt = rows(make_tables(res, plots=False).out / "runtime.csv")["bonn/crowd (dynamic)"]
    assert rt["map /frame"] == "12.0 (n=1)" and rt["map /call"] == "—"


def _results_with_one_run(tmp_path) -> tuple[Path, Path]:
    res = tmp_path / "results"
    gt = tmp_path / "gt.txt"
    _gt(gt)
    make_run(res, "runs/tum/fr3_walking_xyz/a", gt, seq=("tum", "fr3_walking_xyz"))
    return res, res / "runs/tum/fr3_walking_xyz/a"


def test_tables_cli_and_errors(tmp_path):
    from typer.testing import CliRunner

    from dynslam_cli.cli import app

    res, _ = _results_with_one_run(tmp_path)
    r = CliRunner().invoke(app, ["tables", "--results", str(res), "--out", str(tmp_path / "t"), "--no-plots"])
    assert r.exit_code == 0, r.output
    assert "1 completed runs" in r.output and (tmp_path / "t" / "table1_ate.tex").is_file()
    r = CliRunner().invoke(app, ["tables", "--results", str(tmp_path / "nothing"), "--out", str(tmp_path / "t2")])
    assert r.exit_code == 2 and r.output.strip() == f"error: results folder not found: {tmp_path / 'nothing'}"
    assert not (tmp_path / "t2").exists()


@pytest.mark.parametrize("content, problem", [
    ('{"rmse_m": "abc"}', "'rmse_m' is not a number (\"abc\")"),
    ("[0.1, 0.2]", "expected a JSON object, got list"),
    ("{broken", "not readable JSON"),
])
def test_tables_skip_a_bad_ate_json_with_a_warning(tmp_path, content, problem):
    """Fault 9: a wrong-typed or corrupt ate.json is one warning naming the file; the tables go on."""
    from typer.testing import CliRunner

    from dynslam_cli.cli import app

    res, run = _results_with_one_run(tmp_path)
    (run / "ate.json").write_text(content)
    r = CliRunner().invoke(app, ["tables", "--results", str(res), "--out", str(tmp_path / "t"), "--no-plots"])
    assert r.exit_code == 0, r.output
    assert "Traceback" not in r.output
    warnings = r.stderr.strip().splitlines()
    assert len(warnings) == 1 and warnings[0].startswith(f"warning: skipped file {run / 'ate.json'}: ")
    assert problem in warnings[0]
    assert (run / "ate.json").read_text() == content  # the run's files are left as they are
    row = rows(tmp_path / "t" / "table1_ate.csv")["tum/fr3_walking_xyz"]
    assert row["ours dynamic"] == "—" and row["frames"] == "all (30)"  # the run is there, its ATE is not
    assert "1 completed runs" in r.output


def test_tables_skip_incomplete_runs_unless_asked(tmp_path):
    """Fault 10: runs that are not completed are left out with a warning unless --include-incomplete."""
    from typer.testing import CliRunner

    from dynslam_cli.cli import app

    res, run = _results_with_one_run(tmp_path)
    gt = tmp_path / "gt.txt"
    make_run(res, "runs/tum/fr3_walking_xyz/b", gt, seq=("tum", "fr3_walking_xyz"), seed=1, sigma=0.5)
    b = res / "runs/tum/fr3_walking_xyz/b"
    meta = json.loads((b / "run.json").read_text())
    (b / "run.json").write_text(json.dumps({**meta, "status": "interrupted"}))
    args = ["tables", "--results", str(res), "--out", str(tmp_path / "t"), "--no-plots"]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    assert r.stderr.strip() == (f"warning: skipped: run {b} is not completed (run.json status: interrupted); "
                                "pass --include-incomplete to use it anyway")
    assert "1 completed runs" in r.output
    alone = rows(tmp_path / "t" / "table1_ate.csv")["tum/fr3_walking_xyz"]["ours dynamic"]
    assert alone.endswith("(n=1)")
    r = CliRunner().invoke(app, [*args, "--include-incomplete"])
    assert r.exit_code == 0 and r.stderr == "" and "2 runs" in r.output
    assert rows(tmp_path / "t" / "table1_ate.csv")["tum/fr3_walking_xyz"]["ours dynamic"].endswith("(n=2)")
