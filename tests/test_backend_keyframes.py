"""The backend's keyframes and their landmarks (dynslam_cli.backend.keyframes.LandmarkKeyframes)."""

import numpy as np
import pytest

from dynslam_cli.backend.features import Keypoints, project
from dynslam_cli.backend.keyframes import LandmarkKeyframes
from dynslam_cli.backend.tracking import Camera


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


class TestInView:
    """LandmarkKeyframes.in_view: the keyframes whose landmarks a camera would see again."""

    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])

    def _map(self) -> LandmarkKeyframes:
        """Keyframe 0 at the origin looking down +z at 30 points 2 m ahead; keyframe 1 at x = 5
        looking at 10 points 2 m ahead of it; keyframe 2 at the origin looking down -z at 30
        points behind the origin (the same place, the other way)."""
        kfs = LandmarkKeyframes()
        rng = np.random.default_rng(0)
        turn = np.diag([-1.0, 1.0, -1.0, 1.0])  # 180 degrees about y
        for k, (pose, n, ahead) in enumerate([(_pose(0.0), 30, 2.0), (_pose(5.0), 10, 2.0), (turn, 30, -2.0)]):
            kfs.add(10 * k, pose)
            X = np.c_[pose[0, 3] + rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n), np.full(n, ahead)]
            kfs.landmarks.create(k, _keypoints(n), X, pose[:3, 3])
        return kfs

    def test_known_counts_and_order(self):
        kfs = self._map()
        assert kfs.in_view(_pose(0.1), self.K, 100, 100, n=5, min_count=1) == [0]
        assert kfs.in_view(_pose(5.0), self.K, 100, 100, n=5, min_count=1) == [1]
        turn = np.diag([-1.0, 1.0, -1.0, 1.0])
        assert kfs.in_view(turn, self.K, 100, 100, n=5, min_count=1) == [2]  # the points behind, not those ahead
        back = turn.copy()
        back[2, 3] = 4.0  # keyframe 0's points 2 m ahead, but seen from their other side
        assert kfs.in_view(back, self.K, 100, 100, n=5, min_count=1) == []
        back[:3, :3] = np.eye(3)
        back[2, 3] = -0.5  # behind keyframe 0, looking the same way: 2.5 m from its points
        assert kfs.in_view(back, self.K, 100, 100, n=5, min_count=1) == [0]

    def test_exclude_n_and_min_count(self):
        kfs = self._map()
        wide = np.array([[10.0, 0, 50], [0, 10.0, 50], [0, 0, 1]])  # sees x = 0 and x = 5 from 1 m back
        pose = _pose(2.5)
        pose[2, 3] = -8.0  # 10 m from the points: beyond the distance range of the keyframes (2 m)
        assert kfs.in_view(pose, wide, 100, 100, n=5, min_count=1) == []
        pose[2, 3] = 0.0
        both = kfs.in_view(pose, wide, 100, 100, n=5, min_count=1)
        assert both == [0, 1]  # 30 landmarks, then 10
        assert kfs.in_view(pose, wide, 100, 100, n=1, min_count=1) == [0]
        assert kfs.in_view(pose, wide, 100, 100, n=5, min_count=11) == [0]
        assert kfs.in_view(pose, wide, 100, 100, n=5, min_count=1, exclude=[0]) == [1]

    def test_moving_and_culled_landmarks_do_not_count(self):
        kfs = self._map()
        kfs.landmarks.moving[:25] = True
        kfs.landmarks.kill(np.arange(len(kfs.landmarks)) < 3)
        assert kfs.in_view(_pose(0.0), self.K, 100, 100, n=5, min_count=6) == []
        assert kfs.in_view(_pose(0.0), self.K, 100, 100, n=5, min_count=5) == [0]

    def test_empty(self):
        assert LandmarkKeyframes().in_view(np.eye(4), self.K, 100, 100, n=5, min_count=1) == []


class TestAdjustAll:
    CAM = Camera(300.0, 300.0, 160.0, 120.0, 320, 240, 300.0 * 0.08)

    def _scene(self, n_kf=5, seed=0):
        """Keyframes moving sideways (the first at its true pose, the others perturbed by 2 cm) over
        120 static points, and 60 points of instance 5 that move 5 cm a keyframe; every point made by
        keyframe 0 and observed by every keyframe that sees it.  Returns the store and the true poses."""
        rng = np.random.default_rng(seed)
        truth = [_pose(0.1 * k) for k in range(n_kf)]
        X = np.stack([rng.uniform(-1.0, 1.5, 180), rng.uniform(-0.8, 0.8, 180), rng.uniform(2.0, 4.0, 180)], 1)
        origin = np.r_[np.zeros(120, np.int64), np.full(60, 5)]
        kfs = LandmarkKeyframes()
        for k, T in enumerate(truth):
            start = T.copy()
            if k:
                start[:3, 3] += rng.normal(0, 0.02, 3)
            kfs.add(10 * k, start)
            Xk = X + np.where(origin[:, None] == 5, [0.05 * k, 0.0, 0.0], 0.0)  # where each point is now
            uv, z = project(T, Xk, self.CAM.K)
            kp = Keypoints(uv=uv + rng.normal(0, 0.2, uv.shape), des=np.zeros((len(X), 32), np.uint8),
                           octave=np.zeros(len(X), np.int64), depth=z, dsig=0.012 * z * z)
            if k == 0:
                kfs.landmarks.create(0, kp, X.copy(), np.zeros(3), origin)
            else:
                kfs.landmarks.observe(k, np.arange(len(X)), kp)
        return kfs, truth

    def _error(self, kfs, truth) -> float:
        return max(np.linalg.norm(kfs.poses[k][:3, 3] - truth[k][:3, 3]) for k in range(len(truth)))

    def test_recovers_the_poses_without_the_moving_landmarks(self):
        kfs, truth = self._scene()
        first = kfs.poses[0].copy()
        kfs.forget(0, [5])  # instance 5 found to move: its landmarks are left out
        moving = kfs.landmarks.pos[120:].copy()
        before = self._error(kfs, truth)
        res = kfs.adjust_all(self.CAM, huber=2.8)
        assert res is not None and set(res.poses) == {1, 2, 3, 4}
        assert np.array_equal(kfs.poses[0], first)  # the gauge
        assert before > 0.01 and self._error(kfs, truth) < 0.004
        assert np.array_equal(kfs.landmarks.pos[120:], moving)  # not adjusted

    def test_landmarks_that_move_unflagged_pull_the_poses(self):
        kfs, truth = self._scene()
        kfs.adjust_all(self.CAM, huber=2.8)
        flagged, _ = self._scene()
        flagged.forget(0, [5])
        flagged.adjust_all(self.CAM, huber=2.8)
        assert self._error(flagged, truth) < self._error(kfs, truth)

    def test_nothing_to_adjust(self):
        kfs, _ = self._scene(n_kf=1)
        assert kfs.adjust_all(self.CAM, huber=2.8) is None
        empty = LandmarkKeyframes()
        empty.add(0, _pose(0.0))
        empty.add(5, _pose(0.1))
        assert empty.adjust_all(self.CAM, huber=2.8) is None
