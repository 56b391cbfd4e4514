"""ATE: known perturbations, association, alignment modes, evo_ape CLI agreement, Umeyama, rmse_still."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dynslam_cli.errors import DynslamError
from dynslam_cli.eval.ate import compute_ate, evaluate_run_ate, read_tum
from dynslam_cli.geometry.align import apply_similarity, umeyama

VENV_BIN = Path(sys.executable).parent


def make_gt(n=60, seed=0, t0=100.0, dt=1 / 30):
    rng = np.random.default_rng(seed)
    t = t0 + dt * np.arange(n)
    s = np.linspace(0, 2 * np.pi, n)
    xyz = np.stack([np.cos(s), 0.5 * np.sin(2 * s), 0.2 * s], 1) + 0.001 * rng.standard_normal((n, 3))
    rot = Rotation.from_euler("xyz", np.stack([0.1 * np.sin(s), s, 0.05 * s], 1))
    return t, xyz, rot.as_quat()


def write_tum(path: Path, t, xyz, q):
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    lines += [" ".join(f"{v:.9f}" for v in [ti, *p, *qi]) for ti, p, qi in zip(t, xyz, q, strict=False)]
    path.write_text("\n".join(lines) + "\n")
    return path


def rigid(xyz, q, rotvec=(0.3, -0.2, 1.0), trans=(1.0, -2.0, 0.5), scale=1.0):
    r = Rotation.from_rotvec(rotvec)
    return scale * r.apply(xyz) + np.asarray(trans), (r * Rotation.from_quat(q)).as_quat()


@pytest.fixture()
def gt_file(tmp_path):
    return write_tum(tmp_path / "gt.txt", *make_gt())


def test_rigid_copy_has_zero_ate_with_se3_and_origin(tmp_path, gt_file):
    t, xyz, q = make_gt()
    exyz, eq = rigid(xyz, q)
    est = write_tum(tmp_path / "est.txt", t, exyz, eq)
    assert compute_ate(est, gt_file, "se3").rmse_m < 1e-6
    assert compute_ate(est, gt_file, "origin").rmse_m < 1e-6
    assert compute_ate(est, gt_file, "none").rmse_m > 0.5  # a displaced copy is far without alignment


def test_constant_offset_without_alignment_gives_its_length(tmp_path, gt_file):
    t, xyz, q = make_gt()
    est = write_tum(tmp_path / "est.txt", t, xyz + np.array([0.03, 0.04, 0.0]), q)
    r = compute_ate(est, gt_file, "none")
    assert r.rmse_m == pytest.approx(0.05, abs=1e-7)
    assert r.max_m == pytest.approx(0.05, abs=1e-7) and r.std_m < 1e-7
    assert compute_ate(est, gt_file, "se3").rmse_m < 1e-6


def test_sim3_recovers_scale_se3_does_not(tmp_path, gt_file):
    t, xyz, q = make_gt()
    exyz, eq = rigid(xyz, q, scale=0.5)
    est = write_tum(tmp_path / "est.txt", t, exyz, eq)
    r = compute_ate(est, gt_file, "sim3")
    assert r.rmse_m < 1e-6 and r.scale == pytest.approx(2.0, rel=1e-6)
    assert compute_ate(est, gt_file, "se3").rmse_m > 0.1


def test_association_max_diff(tmp_path, gt_file):
    t, xyz, q = make_gt()
    est = write_tum(tmp_path / "est.txt", t + 0.015, xyz, q)
    with pytest.raises(DynslamError, match="associate"):
        compute_ate(est, gt_file, "se3", max_diff=0.01)
    r = compute_ate(est, gt_file, "se3", max_diff=0.02)
    assert r.matched == len(t)
    # only every 3rd estimate stamp is near a GT stamp
    t2 = t.copy()
    t2[np.arange(len(t)) % 3 != 0] += 0.5 / 30
    est2 = write_tum(tmp_path / "est2.txt", t2, xyz, q)
    assert compute_ate(est2, gt_file, "se3", max_diff=0.005).matched == len(range(0, len(t), 3))


def test_known_perturbation_matches_independent_umeyama(tmp_path, gt_file):
    t, xyz, q = make_gt()
    rng = np.random.default_rng(3)
    noisy = xyz + 0.02 * rng.standard_normal(xyz.shape)
    exyz, eq = rigid(noisy, q)
    est = write_tum(tmp_path / "est.txt", t, exyz, eq)
    for mode, with_scale in (("se3", False), ("sim3", True)):
        r = compute_ate(est, gt_file, mode)
        R, tr, s = umeyama(exyz, xyz, with_scale=with_scale)
        err = np.linalg.norm(apply_similarity(exyz, R, tr, s) - xyz, axis=1)
        assert r.rmse_m == pytest.approx(float(np.sqrt(np.mean(err ** 2))), abs=1e-6)
        assert np.allclose(r.rotation, R, atol=1e-6) and r.scale == pytest.approx(s, abs=1e-6)
    # the noise level sets the scale of the error: ATE close to the RMS of the 3-D noise
    assert compute_ate(est, gt_file, "se3").rmse_m == pytest.approx(0.02 * np.sqrt(3), rel=0.15)


def test_umeyama_against_evo_geometry():
    from evo.core.geometry import umeyama_alignment

    rng = np.random.default_rng(1)
    src = rng.standard_normal((40, 3))
    dst = apply_similarity(src, Rotation.from_rotvec([0.4, 0.1, -0.7]).as_matrix(), [1, 2, 3], 1.7)
    dst += 0.01 * rng.standard_normal(dst.shape)
    for ws in (False, True):
        R, t, s = umeyama(src, dst, ws)
        Re, te, se = umeyama_alignment(src.T, dst.T, ws)
        assert np.allclose(R, Re, atol=1e-9) and np.allclose(t, te, atol=1e-9) and s == pytest.approx(se, abs=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0)
    with pytest.raises(DynslamError):
        umeyama(src[:2], dst[:2])


def test_rmse_still_equals_ate_of_a_still_camera(tmp_path, gt_file):
    t, xyz, q = make_gt()
    rng = np.random.default_rng(5)
    # a camera that (almost) never moves: SE(3) alignment moves it onto the GT mean
    jitter = 1e-5 * rng.standard_normal((len(t), 3))
    still = write_tum(tmp_path / "still.txt", t, np.array([5.0, -1.0, 2.0]) + jitter, q)
    r = compute_ate(still, gt_file, "se3")
    expected = float(np.sqrt(np.mean(np.sum((xyz - xyz.mean(0)) ** 2, 1))))
    assert r.rmse_still_m == pytest.approx(expected, abs=1e-9)
    assert r.rmse_m == pytest.approx(r.rmse_still_m, abs=1e-4)
    # without alignment a still camera placed at the GT mean scores exactly rmse_still
    at_mean = write_tum(tmp_path / "mean.txt", t, np.tile(xyz.mean(0), (len(t), 1)), q)
    rn = compute_ate(at_mean, gt_file, "none")
    assert rn.rmse_m == pytest.approx(rn.rmse_still_m, abs=1e-9)
    # origin alignment puts a still camera on the first GT pose
    exact = write_tum(tmp_path / "exact.txt", t, np.tile([5.0, -1.0, 2.0], (len(t), 1)), q)
    ro = compute_ate(exact, gt_file, "origin")
    assert ro.rmse_still_m == pytest.approx(float(np.sqrt(np.mean(np.sum((xyz - xyz[0]) ** 2, 1)))), abs=1e-9)
    assert ro.rmse_m == pytest.approx(ro.rmse_still_m, abs=1e-6)
    # an exactly still camera cannot be SE(3)-aligned (degenerate): a one-line error
    with pytest.raises(DynslamError, match="degenerate"):
        compute_ate(exact, gt_file, "se3")


@pytest.mark.parametrize("flag,mode", [("-a", "se3"), ("--align_origin", "origin")])
def test_equals_evo_ape_console_script(tmp_path, gt_file, flag, mode):
    exe = VENV_BIN / "evo_ape"
    if not exe.is_file():
        pytest.skip(f"evo_ape console script not found beside {sys.executable}")
    t, xyz, q = make_gt()
    rng = np.random.default_rng(7)
    exyz, eq = rigid(xyz + 0.03 * rng.standard_normal(xyz.shape), q)
    est = write_tum(tmp_path / "est.txt", t[::2] + 0.004, exyz[::2], eq[::2])
    home = tmp_path / "home"
    home.mkdir()
    zpath = tmp_path / "res.zip"
    env = {**os.environ, "HOME": str(home), "MPLBACKEND": "Agg"}
    subprocess.run([str(exe), "tum", str(gt_file), str(est), flag, "--t_max_diff", "0.02", "--save_results",
                    str(zpath), "--no_warnings"], check=True, env=env, capture_output=True, timeout=120)
    with zipfile.ZipFile(zpath) as z:
        stats = json.loads(z.read("stats.json"))
    r = compute_ate(est, gt_file, mode, max_diff=0.02)
    assert r.rmse_m == pytest.approx(stats["rmse"], abs=1e-6)
    assert r.max_m == pytest.approx(stats["max"], abs=1e-6)
    assert r.matched == len(t[::2])


def test_bad_inputs_are_one_line_errors(tmp_path, gt_file):
    with pytest.raises(DynslamError, match="not found"):
        compute_ate(tmp_path / "nope.txt", gt_file)
    bad = tmp_path / "bad.txt"
    bad.write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0\n")
    with pytest.raises(DynslamError, match="line 2"):
        read_tum(bad)
    nan = tmp_path / "nan.txt"
    nan.write_text("1.0 nan 0 0 0 0 0 1\n")
    with pytest.raises(DynslamError, match="NaN"):
        read_tum(nan)
    with pytest.raises(DynslamError, match="alignment"):
        compute_ate(gt_file, gt_file, "bogus")


def _fake_run(run_dir: Path, gt_file: Path, est_xyz_noise=0.01, seed=0):
    t, xyz, q = make_gt()
    rng = np.random.default_rng(seed)
    run_dir.mkdir(parents=True)
    write_tum(run_dir / "traj_est.txt", t, xyz + est_xyz_noise * rng.standard_normal(xyz.shape), q)
    (run_dir / "run.json").write_text(json.dumps({"status": "completed", "sequence": {
        "spec": "synth/x", "dataset": "synth", "name": "x", "groundtruth": str(gt_file)}}))
    return run_dir


def test_evaluate_run_writes_files(tmp_path, gt_file):
    run = _fake_run(tmp_path / "run", gt_file)
    r = evaluate_run_ate(run)
    data = json.loads((run / "ate.json").read_text())
    assert data["rmse_m"] == pytest.approx(r.rmse_m) and data["gt_file"] == str(gt_file)
    assert data["matched"] == 60 and data["alignment"] == "se3" and "rmse_still_m" in data
    assert (run / "ate.png").stat().st_size > 1000
    with pytest.raises(DynslamError, match="run folder not found"):
        evaluate_run_ate(tmp_path / "missing")


def test_evaluate_run_online_scores_traj_online_beside_the_final(tmp_path, gt_file):
    run = _fake_run(tmp_path / "run", gt_file, est_xyz_noise=0.001)
    with pytest.raises(DynslamError, match="traj_online.txt not found"):
        evaluate_run_ate(run, online=True, plot=False)
    t, xyz, q = make_gt()
    write_tum(run / "traj_online.txt", t, xyz + 0.05 * np.random.default_rng(1).standard_normal(xyz.shape), q)
    final = evaluate_run_ate(run, plot=False)
    online = evaluate_run_ate(run, online=True)
    assert online.rmse_m > 10 * final.rmse_m  # each file scored on its own
    assert json.loads((run / "ate.json").read_text())["rmse_m"] == pytest.approx(final.rmse_m)
    assert json.loads((run / "ate_online.json").read_text())["rmse_m"] == pytest.approx(online.rmse_m)
    assert (run / "ate_online.png").is_file()


def test_cli_eval_ate(tmp_path, gt_file):
    from typer.testing import CliRunner

    from dynslam_cli.cli import app

    run = _fake_run(tmp_path / "run", gt_file)
    res = CliRunner().invoke(app, ["eval-ate", str(run), "--align", "sim3", "--max-diff", "0.01", "--no-plot"])
    assert res.exit_code == 0, res.output
    assert json.loads((run / "ate.json").read_text())["alignment"] == "sim3"
    assert "ATE RMSE" in res.output
    t, xyz, q = make_gt()
    write_tum(run / "traj_online.txt", t, xyz, q)
    res = CliRunner().invoke(app, ["eval-ate", str(run), "--online", "--no-plot"])
    assert res.exit_code == 0 and "online ATE RMSE" in res.output and (run / "ate_online.json").is_file()
    (run / "traj_est.txt").write_text("garbage\n")
    res = CliRunner().invoke(app, ["eval-ate", str(run)])
    assert res.exit_code == 2 and "error:" in res.output and "line 1" in res.output
    res = CliRunner().invoke(app, ["eval-ate", str(tmp_path / "none")])
    assert res.exit_code == 2 and "run folder not found" in res.output


def test_real_bonn_groundtruth_against_evo_ape(tmp_path, bonn_clip):
    """Estimate at the clip's rgb timestamps (nearest GT pose + noise) vs the raw Bonn ground truth."""
    exe = VENV_BIN / "evo_ape"
    if not exe.is_file():
        pytest.skip(f"evo_ape console script not found beside {sys.executable}")
    gt_file = bonn_clip / "groundtruth.txt"
    g_t, g_xyz, g_q = read_tum(gt_file)
    rgb_t = np.array([float(ln.split()[0]) for ln in (bonn_clip / "rgb.txt").read_text().splitlines()
                      if ln.strip() and not ln.startswith("#")])
    idx = np.abs(g_t[None, :] - rgb_t[:, None]).argmin(1)
    rng = np.random.default_rng(0)
    est = write_tum(tmp_path / "est.txt", rgb_t, g_xyz[idx] + 0.02 * rng.standard_normal((len(idx), 3)), g_q[idx])
    home = tmp_path / "home"
    home.mkdir()
    zpath = tmp_path / "res.zip"
    subprocess.run([str(exe), "tum", str(gt_file), str(est), "-a", "--t_max_diff", "0.02", "--save_results",
                    str(zpath), "--no_warnings"], check=True, capture_output=True, timeout=120,
                   env={**os.environ, "HOME": str(home), "MPLBACKEND": "Agg"})
    with zipfile.ZipFile(zpath) as z:
        stats = json.loads(z.read("stats.json"))
    r = compute_ate(est, gt_file, "se3", max_diff=0.02)
    assert r.rmse_m == pytest.approx(stats["rmse"], abs=1e-6)
    # this clip barely moves: a still camera scores only ~0.09 m
    assert r.matched == 150 and 0.05 < r.rmse_still_m < 0.15 and r.rmse_still_m > 2 * r.rmse_m


def _set_status(run_dir: Path, status):
    meta = json.loads((run_dir / "run.json").read_text())
    if status is None:
        meta.pop("status")
    else:
        meta["status"] = status
    (run_dir / "run.json").write_text(json.dumps(meta))


@pytest.mark.parametrize("status", ["running", "failed", "interrupted", None])
def test_cli_eval_ate_refuses_incomplete_run(tmp_path, gt_file, status):
    from typer.testing import CliRunner

    from dynslam_cli.cli import app

    run = _fake_run(tmp_path / "run", gt_file)
    (run / "ate.json").write_text('{"rmse_m": 9.0}')  # from an earlier evaluation: must stay as it is
    _set_status(run, status)
    res = CliRunner().invoke(app, ["eval-ate", str(run), "--no-plot"])
    assert res.exit_code == 2
    assert res.output.strip() == (f"error: run {run} is not completed (run.json status: {status}); "
                                  "pass --include-incomplete to use it anyway")
    assert (run / "ate.json").read_text() == '{"rmse_m": 9.0}'
    res = CliRunner().invoke(app, ["eval-ate", str(run), "--no-plot", "--include-incomplete"])
    assert res.exit_code == 0, res.output
    assert json.loads((run / "ate.json").read_text())["rmse_m"] < 0.1
    (run / "run.json").unlink()  # a folder without run.json is not a completed run either
    res = CliRunner().invoke(app, ["eval-ate", str(run), "--no-plot"])
    assert res.exit_code == 2 and "(no run.json)" in res.output


def test_cli_eval_ate_skips_incomplete_among_several(tmp_path, gt_file):
    from typer.testing import CliRunner

    from dynslam_cli.cli import app

    ok = _fake_run(tmp_path / "ok", gt_file)
    bad = _fake_run(tmp_path / "bad", gt_file, seed=1)
    _set_status(bad, "failed")
    res = CliRunner().invoke(app, ["eval-ate", str(ok), str(bad), "--no-plot"])
    assert res.exit_code == 0, res.output
    warnings = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert warnings == [f"warning: skipped: run {bad} is not completed (run.json status: failed); "
                        "pass --include-incomplete to use it anyway"]
    assert (ok / "ate.json").is_file() and not (bad / "ate.json").exists()
    res = CliRunner().invoke(app, ["eval-ate", str(ok), str(bad), "--no-plot", "--include-incomplete"])
    assert res.exit_code == 0 and (bad / "ate.json").is_file() and "warning" not in res.output
    _set_status(ok, "running")
    before = (ok / "ate.json").read_text()
    res = CliRunner().invoke(app, ["eval-ate", str(ok), str(bad), "--no-plot"])
    assert res.exit_code == 2 and res.output.strip().splitlines()[-1] == (
        "error: none of the 2 run folders is completed; pass --include-incomplete to evaluate them anyway")
    assert (ok / "ate.json").read_text() == before
