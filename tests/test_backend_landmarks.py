"""Landmark bookkeeping and culling (dynslam_cli.backend.landmarks)."""

import numpy as np

from dynslam_cli.backend.features import Keypoints
from dynslam_cli.backend.landmarks import LandmarkMap


def _kps(n, seed=0):
    rng = np.random.default_rng(seed)
    return Keypoints(rng.uniform(0, 300, (n, 2)), rng.integers(0, 256, (n, 32), dtype=np.uint8),
                     rng.uniform(1, 3, n), np.zeros(n, np.int64))


def _map_with(n=5):
    lm = LandmarkMap()
    X = np.random.default_rng(1).normal(size=(n, 3)) + [0, 0, 3]
    ids = lm.create(0, _kps(n), X, np.zeros(3))
    return lm, ids


def test_create_and_observe():
    lm, ids = _map_with(5)
    assert list(ids) == [0, 1, 2, 3, 4] and lm.n_alive == 5
    assert np.array_equal(lm.n_obs(), np.ones(5))
    lm.observe(1, ids[:2], _kps(2, seed=3))
    assert np.array_equal(lm.n_obs(), [2, 2, 1, 1, 1])
    assert np.array_equal(lm.seen_by([1]), [0, 1])
    kfs, counts = lm.covisible(ids[:3])
    assert list(kfs) == [0, 1] and list(counts) == [3, 2]


def test_cull_drops_rarely_found_landmark():
    lm, ids = _map_with(3)
    lm.observe(1, ids, _kps(3, seed=2))
    for _ in range(9):  # landmark 0 projected into 9 more frames, matched in none; 1 and 2 matched in all
        lm.count(visible=ids, found=ids[1:])
    assert lm.cull_recent(current_kf=1) == 1
    assert list(lm.alive) == [False, True, True]
    assert 0 not in lm.obs_lm  # its observations went with it


def test_cull_drops_landmark_seen_by_one_keyframe_after_two():
    lm, ids = _map_with(3)
    lm.observe(1, ids[:2], _kps(2, seed=2))
    assert lm.cull_recent(current_kf=1) == 0  # too young to judge
    assert lm.cull_recent(current_kf=2) == 1
    assert list(lm.alive) == [True, True, False]
    assert lm.cull_recent(current_kf=5) == 0  # old landmarks are no longer culled by these rules


def test_outlier_observations_are_dropped_and_lonely_landmarks_culled():
    lm, ids = _map_with(3)
    lm.observe(1, ids, _kps(3, seed=2))
    lm.observe(2, ids[:1], _kps(1, seed=4))
    drop = (lm.obs_kf == 1) & np.isin(lm.obs_lm, [0, 1])
    assert lm.drop_observations(drop) == 1  # landmark 1 is left with one observation; 0 still has two
    assert list(lm.alive) == [True, False, True]
    assert np.array_equal(lm.n_obs()[[0, 2]], [2, 2])


def test_state_dict_round_trip():
    lm, ids = _map_with(4)
    lm.observe(1, ids[:2], _kps(2, seed=2))
    lm.count(ids, ids[:1])
    other = LandmarkMap()
    other.load_state_dict(lm.state_dict())
    for k, v in lm.state_dict().items():
        assert np.array_equal(v, other.state_dict()[k]) and v.dtype == other.state_dict()[k].dtype, k
