"""Frames solved again against the finished map (dynslam_cli.backend.refine)."""

import numpy as np
import pytest

from dynslam_cli.backend.features import Keypoints
from dynslam_cli.backend.refine import FrameMatches, refine_poses
from dynslam_cli.backend.tracking import Camera
from dynslam_cli.geometry.lie import so3_exp_np

CAM = Camera(300.0, 300.0, 160.0, 120.0, 320, 240, 300.0 * 0.08)


def _landmarks(n=60, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1.0, 1.0, n), rng.uniform(2.0, 4.0, n)])


def _pose(t=(0.0, 0.0, 0.0), w=(0.0, 0.0, 0.0)):
    T = np.eye(4)
    T[:3, :3] = so3_exp_np(np.asarray(w, float))
    T[:3, 3] = t
    return T


def _observe(T_c2w, X):
    """Exact keypoints of world points X seen from T_c2w (pixels, depth, octave 0, depth sigma 1 cm)."""
    pc = (X - T_c2w[:3, 3]) @ T_c2w[:3, :3]
    uv = np.column_stack([CAM.fx * pc[:, 0] / pc[:, 2] + CAM.cx, CAM.fy * pc[:, 1] / pc[:, 2] + CAM.cy])
    n = len(X)
    return Keypoints(uv, np.zeros((n, 32), np.uint8), pc[:, 2].copy(), np.zeros(n, np.int64), np.full(n, 0.01))


class TestFrameMatches:
    def test_set_get_drop(self):
        m = FrameMatches()
        X = _landmarks(5)
        m.set(3, np.arange(5), _observe(_pose(), X))
        ids, kp = m.get(3)
        assert len(m) == 1 and m.frames() == [3] and np.array_equal(ids, np.arange(5)) and len(kp) == 5
        assert kp.des.shape == (5, 0)  # descriptors are not kept
        m.set(3, np.arange(2), _observe(_pose(), X[:2]))  # tracked again: replaced
        assert len(m.get(3)[0]) == 2
        m.drop(3)
        assert len(m) == 0 and m.get(3) is None
        m.drop(3)  # nothing to drop: fine

    def test_lengths_must_match(self):
        with pytest.raises(ValueError, match="3 landmark ids for 5 keypoints"):
            FrameMatches().set(0, np.arange(3), _observe(_pose(), _landmarks(5)))

    def test_remap_follows_compaction(self):
        m = FrameMatches()
        m.set(0, np.array([0, 2, 4]), _observe(_pose(), _landmarks(3)))
        m.remap(None)  # nothing compacted
        assert np.array_equal(m.get(0)[0], [0, 2, 4])
        m.remap(np.array([0, -1, 1, -1, 2]))  # landmarks 1 and 3 dropped
        assert np.array_equal(m.get(0)[0], [0, 1, 2])
        m.remap(np.array([-1, 0, 1]))
        assert np.array_equal(m.get(0)[0], [-1, 0, 1])
        m.remap(np.array([0, 1]))  # a dropped match stays dropped (not the last landmark's new id)
        assert np.array_equal(m.get(0)[0], [-1, 0, 1])

    def test_state_dict_round_trip(self):
        m = FrameMatches()
        X = _landmarks(7)
        m.set(1, np.arange(4), _observe(_pose(), X[:4]))
        m.set(5, np.arange(3) + 4, _observe(_pose((0.1, 0, 0)), X[4:]))
        m.set(6, np.zeros(0, np.int64), _observe(_pose(), X[:0]))  # a frame with no match
        back = FrameMatches()
        back.load_state_dict({k: np.array(v) for k, v in m.state_dict().items()})
        assert back.frames() == [1, 5, 6]
        for f in (1, 5, 6):
            (ia, ka), (ib, kb) = m.get(f), back.get(f)
            assert np.array_equal(ia, ib)
            for a, b in ((ka.uv, kb.uv), (ka.depth, kb.depth), (ka.octave, kb.octave), (ka.dsig, kb.dsig)):
                assert np.array_equal(a, b)
        empty = FrameMatches()
        empty.load_state_dict(FrameMatches().state_dict())
        assert len(empty) == 0


class TestRefinePoses:
    def test_recovers_the_pose_the_matches_say(self):
        X = _landmarks()
        truth = _pose((0.05, -0.02, 0.1), (0.01, -0.03, 0.02))
        m = FrameMatches()
        m.set(1, np.arange(len(X)), _observe(truth, X))
        poses = np.stack([_pose(), _pose((0.08, 0.0, 0.12), (0.0, -0.02, 0.0))])  # row 1 a few cm off
        out, n = refine_poses(CAM, poses, m, X, np.ones(len(X), bool), min_matches=20, huber=2.8)
        assert n == 1 and np.array_equal(out[0], poses[0])  # a row without matches (a keyframe) stays
        assert np.allclose(out[1], truth, atol=1e-6)
        assert np.array_equal(poses[1], _pose((0.08, 0.0, 0.12), (0.0, -0.02, 0.0)))  # the input is not changed

    def test_unusable_and_dropped_landmarks_are_left_out(self):
        X = _landmarks()
        truth = _pose((0.05, 0.0, 0.0))
        m = FrameMatches()
        ids = np.arange(len(X))
        ids[:5] = -1  # compacted away
        m.set(0, ids, _observe(truth, X))
        usable = np.ones(len(X), bool)
        moved = X.copy()
        moved[5:15] += 0.5  # found to move since: positions of no use
        usable[5:15] = False
        out, n = refine_poses(CAM, _pose()[None], m, moved, usable, min_matches=20, huber=2.8)
        assert n == 1 and np.allclose(out[0], truth, atol=1e-6)

    def test_too_few_matches_keep_the_pose(self):
        X = _landmarks(30)
        m = FrameMatches()
        m.set(0, np.arange(30), _observe(_pose((0.05, 0, 0)), X))
        usable = np.zeros(30, bool)
        usable[:19] = True
        start = _pose()[None]
        out, n = refine_poses(CAM, start, m, X, usable, min_matches=20, huber=2.8)
        assert n == 0 and np.array_equal(out, start)
        out, n = refine_poses(CAM, start, m, X, np.ones(30, bool), min_matches=20, huber=2.8)
        assert n == 1

    def test_rows_past_the_trajectory_are_ignored(self):
        X = _landmarks()
        m = FrameMatches()
        m.set(4, np.arange(len(X)), _observe(_pose(), X))
        out, n = refine_poses(CAM, _pose()[None], m, X, np.ones(len(X), bool), min_matches=20, huber=2.8)
        assert n == 0
