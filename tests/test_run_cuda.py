"""The whole pipeline on a CUDA device (skipped where there is none): both modes end to end, with the
encoder the defaults use, a resume across the device's checkpoint, and the CUDA run's trajectory
beside the CPU run's on the same tiny walker."""

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from dynslam_cli.cli import app
from tiny_runs import early_check, read_traj as _traj, tiny_sets, walker_fixture  # noqa: F401 (early_check: an autouse fixture)

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")

TINY = tiny_sets()
walker = walker_fixture(96, 72, 10)


def _run(walker, out, *args):
    res = CliRunner().invoke(app, ["run", "--seq", str(walker), "--out", str(out), "-q", *args] + TINY)
    assert res.exit_code == 0, res.output
    return json.loads((out / "run.json").read_text())


@pytest.mark.parametrize("mode", ["static", "dynamic"])
def test_cuda_run_completes_and_follows_the_cpu_run(walker, tmp_path, mode):
    meta = _run(walker, tmp_path / "on_gpu", "--mode", mode, "--device", "cuda", "--save-masks")
    assert meta["status"] == "completed"
    _run(walker, tmp_path / "on_cpu", "--mode", mode, "--device", "cpu")
    cuda, cpu = _traj(tmp_path / "on_gpu" / "traj_est.txt"), _traj(tmp_path / "on_cpu" / "traj_est.txt")
    assert cuda.shape == cpu.shape == (10, 8) and np.isfinite(cuda).all()
    # float results differ between devices; the tiny clip moves about 2 cm per frame
    assert np.abs(cuda[:, 1:4] - cpu[:, 1:4]).max() < 0.05
    assert (tmp_path / "on_gpu" / "mesh.ply").stat().st_size > 0


def test_cuda_run_with_the_default_encoder_and_resume(walker, tmp_path):
    args = ["run", "--seq", str(walker), "--mode", "dynamic", "--device", "cuda", "-q"] + TINY + [
        "--set", "motion.encoder=effnet-lite0", "--set", "run.checkpoint_every=4"]
    part = tmp_path / "part"
    r = CliRunner().invoke(app, args + ["--out", str(part), "--stop-after", "5"])
    assert r.exit_code == 0, r.output
    assert json.loads((part / "run.json").read_text())["status"] == "interrupted"
    r = CliRunner().invoke(app, args + ["--out", str(part), "--resume"])
    assert r.exit_code == 0, r.output
    meta = json.loads((part / "run.json").read_text())
    assert meta["status"] == "completed" and meta["encoder"] == "effnet-lite0 on torch"  # the network on the GPU
    assert _traj(part / "traj_est.txt").shape == (10, 8)


def test_cuda_peak_memory_is_the_runs_own(walker, tmp_path):
    # a GiB held on the GPU and released before the run: the run's peak must not count it
    big = torch.empty(2 ** 28, dtype=torch.float32, device="cuda")
    del big
    _run(walker, tmp_path / "run", "--mode", "static", "--device", "cuda")
    timing = json.loads((tmp_path / "run" / "timing.json").read_text())
    assert 0 < timing["peak_gpu_mb"] < 1024
