"""The backend's keyframes and their landmarks (dynslam_cli.backend.keyframes.LandmarkKeyframes)."""

import numpy as np
import pytest

from dynslam_cli.backend.features import Keypoints
from dynslam_cli.backend.keyframes import LandmarkKeyframes


def _keypoints(n: int) -> Keypoints:
    rng = np.random.default_rng(n)
    return Keypoints(uv=rng.uniform(0, 100, (n, 2)), des=rng.integers(0, 256, (n, 32)).astype(np.uint8),
                     octave=np.zeros(n, np.int64), depth=np.full(n, 2.0), dsig=np.full(n, 0.01))


def _pose(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


class TestLandmarkKeyframes:
    def _two(self) -> LandmarkKeyframes:
        kfs = LandmarkKeyframes()
        for k, (frame, origin) in enumerate([(0, [3, 3, 4]), (7, [3, -1])]):
            assert kfs.add(frame, _pose(0.1 * k)) == k
            kp = _keypoints(len(origin))
            kfs.landmarks.create(k, kp, np.ones((len(origin), 3)), np.zeros(3), np.array(origin))
        return kfs

    def test_add_and_read_only_views(self):
        kfs = self._two()
        assert len(kfs) == 2 and kfs.frames.tolist() == [0, 7] and kfs.poses.shape == (2, 4, 4)
        with pytest.raises(ValueError):
            kfs.poses[0, 0, 3] = 1.0  # changes go through set_pose
        with pytest.raises(ValueError):
            kfs.frames[0] = 3
        kfs.set_pose(1, _pose(0.5))
        assert kfs.poses[1, 0, 3] == 0.5

    def test_index_of(self):
        kfs = self._two()
        assert (kfs.index_of(0), kfs.index_of(7), kfs.index_of(5)) == (0, 1, -1)

    def test_forget_leaves_out_only_that_keyframes_landmarks_of_the_instances(self):
        kfs = self._two()
        assert kfs.forget(5, [3]) == 0  # frame 5 is no keyframe
        assert kfs.forget(0, [3]) == 2
        assert kfs.landmarks.moving.tolist() == [True, True, False, False, False]
        assert kfs.forget(7, [3]) == 1  # its landmark of unknown origin (-1) stays
        assert kfs.landmarks.moving.tolist() == [True, True, False, True, False]
        assert kfs.forget(0, []) == 0  # called static again: back
        assert kfs.landmarks.moving.tolist() == [False, False, False, True, False]

    def test_state_round_trip(self):
        kfs = self._two()
        kfs.forget(0, [4])
        back = LandmarkKeyframes()
        back.load_state_dict({k: np.array(v) for k, v in kfs.state_dict().items()})
        assert np.array_equal(back.frames, kfs.frames) and np.array_equal(back.poses, kfs.poses)
        for k, v in kfs.landmarks.state_dict().items():
            assert np.array_equal(back.landmarks.state_dict()[k], v), k
        back.set_pose(0, _pose(1.0))  # the copy is its own
        assert kfs.poses[0, 0, 3] == 0.0
