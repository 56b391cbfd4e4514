"""benchmarks/bench_smoothing.py: stored runs re-smoothed (the benchmark itself is run by hand)."""

import json

import numpy as np
import pytest

import benchmark_scripts  # tests/benchmark_scripts.py

B = benchmark_scripts.load("bench_smoothing")


def _tum(path, stamps, xyz):
    q = np.tile([0.0, 0.0, 0.0, 1.0], (len(stamps), 1))
    np.savetxt(path, np.c_[stamps, xyz, q], fmt=["%.6f"] + ["%.7f"] * 7, header="timestamp tx ty tz qx qy qz qw")


@pytest.fixture()
def run(tmp_path):
    """A run folder: a smooth ground truth, the unsmoothed trajectory with 3 mm noise and two frames 15 cm off
    before the last, the stored traj_est.txt a copy of it, run.json naming the ground truth."""
    t = 1000.0 + np.arange(200) / 30.0
    s = t - t[0]
    gt = np.stack([0.2 * np.sin(0.5 * s), 0.1 * s, 0.05 * np.cos(0.3 * s)], 1)
    z = gt + np.random.default_rng(0).normal(0, 0.003, gt.shape)
    z[-3:-1, 0] += 0.15
    _tum(tmp_path / "groundtruth.txt", t, gt)
    d = tmp_path / "run"
    d.mkdir()
    _tum(d / "traj_unsmoothed.txt", t, z)
    _tum(d / "traj_est.txt", t, z)
    (d / "run.json").write_text(json.dumps({"sequence": {"groundtruth": str(tmp_path / "groundtruth.txt")}}))
    return d


class TestRunFolders:
    def test_folders_and_globs_once_each(self, run, tmp_path):
        (tmp_path / "empty").mkdir()
        found = B.run_folders([str(run), str(tmp_path / "*"), str(tmp_path / "empty")])
        assert found == [run]


class TestResmooth:
    def test_the_excursion_is_smoothed_out(self, run):
        r = B.resmooth(run)
        assert r["stored"] == pytest.approx(r["unsmoothed"])  # the stored file is the unsmoothed one here
        assert r["resmoothed"] < 0.5 * r["unsmoothed"] and r["downweighted"] >= 2 and r["q"] > 0

    def test_no_ground_truth_gives_none(self, run):
        (run / "run.json").write_text(json.dumps({"sequence": {"groundtruth": None}}))
        assert B.resmooth(run) is None


class TestMain:
    def test_table_and_sums(self, run, capsys):
        assert B.main([str(run)]) == 0
        out = capsys.readouterr().out
        assert str(run) in out and "1 runs: unsmoothed" in out

    def test_nothing_found(self, tmp_path, capsys):
        assert B.main([str(tmp_path / "nothing*")]) == 0
        assert "no run folder" in capsys.readouterr().out
