"""The backend's sparse vote that an instance moved (dynslam_cli.motion.reprojection)."""

import numpy as np
import pytest
from scipy.stats import binom

from dynslam_cli.motion import reprojection as R
from dynslam_cli.motion.reprojection import moving_by_reprojection


def _frame(groups, h=40, w=100, seed=0):
    """An id image with instance k+1 in columns [10k, 10k+10) and, per group (instance id, matches,
    failures), that many keypoints on it, the first ``failures`` failing to reproject."""
    rng = np.random.default_rng(seed)
    ids = np.zeros((h, w), np.int32)
    for k in range(w // 10):
        ids[:, 10 * k:10 * k + 10] = k + 1
    uv, ok = [], []
    for inst, n, bad in groups:
        col = 10 * (inst - 1) if inst > 0 else None
        u = rng.uniform(col, col + 9, n) if col is not None else rng.uniform(0, w - 1, n)
        uv.append(np.stack([u, rng.uniform(0, h - 1, n)], 1))
        ok.append(np.arange(n) >= bad)
    return ids, np.concatenate(uv), np.concatenate(ok)


class TestMovingByReprojection:
    def test_an_instance_whose_matches_stop_reprojecting_moved(self):
        ids, uv, ok = _frame([(1, 200, 6), (2, 40, 30), (3, 40, 2)])
        out = moving_by_reprojection(ids, uv, ok, 4)
        assert out.tolist() == [False, True, False, False]  # instance 4 has no matches

    def test_known_threshold(self):
        # the frame's rate: 14 of 400 = 3.5 % < the gate's 5 %, so 5 %; instance 2: 20 matches
        need = next(b for b in range(21) if binom.sf(b - 1, 20, R.GATE_FALSE_ALARM) < R.ALPHA)
        for bad, moved in ((need - 1, False), (need, True)):
            ids, uv, ok = _frame([(1, 380, 14 - bad), (2, 20, bad)])
            assert moving_by_reprojection(ids, uv, ok, 2)[1] == moved, bad

    def test_a_frame_where_everything_fails_votes_for_nothing(self):
        # the pose itself is bad (or the scene moved as a whole): no instance stands out
        ids, uv, ok = _frame([(1, 50, 40), (2, 50, 41), (3, 50, 39)])
        assert not moving_by_reprojection(ids, uv, ok, 3).any()

    def test_one_failure_of_a_few_matches_is_not_evidence(self):
        ids, uv, ok = _frame([(1, 300, 0), (2, 10, 1)])
        assert not moving_by_reprojection(ids, uv, ok, 2).any()

    def test_background_id_zero_is_never_voted(self):
        ids = np.zeros((40, 100), np.int32)
        ids[:, :10] = 1
        uv = np.stack([np.r_[np.full(30, 50.0), np.full(30, 5.0)], np.full(60, 20.0)], 1)
        ok = np.r_[np.zeros(30, bool), np.ones(30, bool)]  # the failures are all on id 0
        assert moving_by_reprojection(ids, uv, ok, 1).tolist() == [False]

    @pytest.mark.parametrize("count", [0, 3])
    def test_no_matches(self, count):
        out = moving_by_reprojection(np.zeros((4, 4), np.int32), np.zeros((0, 2)), np.zeros(0, bool), count)
        assert out.shape == (count,) and not out.any()

    def test_does_not_import_scipy_stats(self):
        # scipy.stats costs 0.6-1.7 s to import, paid at a run's first check when this module used binom.sf
        import subprocess
        import sys

        code = ("import sys, numpy as np\nfrom dynslam_cli.motion.reprojection import moving_by_reprojection\n"
                "ids = np.ones((4, 4), np.int32)\n"
                "moving_by_reprojection(ids, np.ones((3, 2)), np.array([True, False, False]), 1)\n"
                "print('scipy.stats' in sys.modules)\n")
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
        assert out.strip() == "False"
