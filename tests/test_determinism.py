"""The same seed, thread count and machine give byte-identical results (issue 19, item 12).

Two runs of a tiny clip at 2 threads, static and dynamic mode, must write the same trajectory,
mesh, masks and classifier updates.  Bundle adjustment draws 4096 rays per iteration so that
autograd's backward of the per-ray pose gather is large enough for torch to split it over the
threads: with plain indexing (``T[own]``) and torch's default algorithms it scatter-adds with
atomic float adds, and the two runs drift apart.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys

import pytest
import torch
from typer.testing import CliRunner

from dynslam_cli.cli import app
from dynslam_cli.utils.threads import deterministic_torch
from tiny_runs import early_check, tiny_sets, walker_fixture  # noqa: F401 (early_check: an autouse fixture)

SMALL = tiny_sets(first_iters=15, ba_rays=4096, threads=2)


walker = walker_fixture(80, 60, 7)


def _outputs(run) -> dict:
    """sha1 of every result file that must repeat (not run.json, timing.json: times)."""
    files = [run / "traj_est.txt", run / "mesh.ply", run / "classifier_updates.jsonl", run / "frames.jsonl"]
    files += sorted((run / "masks").glob("*.png")) if (run / "masks").is_dir() else []
    return {str(p.relative_to(run)): hashlib.sha1(p.read_bytes()).hexdigest() for p in files if p.is_file()}


# backend false: Co-SLAM's dense tracking, whose bundle adjustment moves the keyframe poses (the
# path of the race); true (the default): poses from the keyframe backend, the neural BA trains the map
@pytest.mark.parametrize("mode,backend", [("static", "false"), ("dynamic", "false"), ("dynamic", "true")])
def test_same_seed_and_threads_give_identical_files(walker, tmp_path, mode, backend):
    got = []
    for name in ("a", "b"):
        out = tmp_path / name
        args = ["run", "--seq", str(walker), "--mode", mode, "--out", str(out), "--seed", "0", "-q",
                "--set", f"tracking.backend={backend}"] + SMALL
        res = CliRunner().invoke(app, args + (["--save-masks"] if mode == "dynamic" else []))
        assert res.exit_code == 0, res.output
        assert json.loads((out / "run.json").read_text())["threads"] == 2
        got.append(_outputs(out))
    assert "traj_est.txt" in got[0] and "mesh.ply" in got[0]
    if mode == "dynamic":
        assert any(k.startswith("masks/") for k in got[0]) and "classifier_updates.jsonl" in got[0]
    assert got[0] == got[1]


def test_pose_gather_backward_repeats_bitwise_with_two_threads():
    # bundle adjustment's gather of each ray's pose (few poses, many rays): its backward must add
    # the rays' gradients in the same order every time; with deterministic_torch() plain indexing
    # does too (it runs serially instead of with atomic adds)
    old_threads, old_det = torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()
    gen = torch.Generator().manual_seed(0)
    T = torch.randn(3, 4, 4, dtype=torch.float32, requires_grad=True)
    own = torch.randint(0, 3, (16384,), generator=gen)
    go = torch.randn(16384, 4, 4, generator=gen)
    try:
        torch.set_num_threads(2)
        deterministic_torch()
        for gather in (lambda: T.index_select(0, own), lambda: T[own]):
            grads = set()
            for _ in range(8):
                T.grad = None
                gather().backward(go)
                grads.add(T.grad.numpy().tobytes())
            assert len(grads) == 1
        # and the gradient is the sum it should be
        ref = torch.zeros(3, 4, 4, dtype=torch.float64).index_add_(0, own, go.double())
        assert torch.allclose(T.grad.double(), ref, rtol=1e-4, atol=1e-3)
    finally:
        torch.set_num_threads(old_threads)
        torch.use_deterministic_algorithms(old_det)


def test_set_threads_starts_numba_on_the_chosen_layer():
    # numba.set_num_threads starts numba's thread pool: the layer must be chosen before it (a
    # fresh interpreter: the layer is fixed once the pool runs)
    code = ("import os; os.environ.pop('NUMBA_THREADING_LAYER', None)\n"
            "from dynslam_cli.utils.threads import set_threads\n"
            "set_threads(2)\n"
            "import numba, numpy as np\n"
            "@numba.njit(parallel=True)\n"
            "def f(a):\n"
            "    for i in numba.prange(a.shape[0]):\n"
            "        a[i] += 1.0\n"
            "f(np.zeros(64))\n"
            "print(numba.threading_layer())\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip().splitlines()[-1] == "workqueue"
