"""Landmark bookkeeping and culling (dynslam_cli.backend.landmarks)."""

import numpy as np

from dynslam_cli.backend.features import Keypoints
from dynslam_cli.backend.landmarks import LandmarkMap


def _kps(n, seed=0):
    rng = np.random.default_rng(seed)
    return Keypoints(rng.uniform(0, 300, (n, 2)), rng.integers(0, 256, (n, 32), dtype=np.uint8),
                     rng.uniform(1, 3, n), np.zeros(n, np.int64), np.full(n, 0.01))


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


def test_compact_drops_dead_rows_and_keeps_every_live_landmark():
    lm, ids = _map_with(6)
    lm.create(1, _kps(4, seed=5), np.ones((4, 3)), np.zeros(3), origin=[3, 4, 5, 6])
    lm.observe(1, ids[[1, 2, 4]], _kps(3, seed=2))
    lm.observe(2, np.array([2, 7, 9]), _kps(3, seed=6))
    lm.count(np.arange(10), np.arange(0, 10, 2))
    lm.set_moving(1, [4])  # landmark 7
    dead = np.zeros(10, bool)
    dead[[0, 3, 8]] = True
    lm.kill(dead)
    before = lm.state_dict()
    live = np.flatnonzero(~dead)
    obs_before = {(int(k), int(j)): i for i, (k, j) in enumerate(zip(before["obs_kf"], before["obs_lm"], strict=False))}
    assert lm.compact() is None and len(lm) == 10  # 3 of 10 dead: under the threshold (and the minimum)
    remap = lm.compact(force=True)
    assert len(lm) == lm.n_alive == 7 and np.array_equal(remap[live], np.arange(7)) and (remap[dead] == -1).all()
    for k in ("pos", "des", "octave", "dist", "first_kf", "origin", "moving", "visible", "found", "alive"):
        assert np.array_equal(getattr(lm, k), before[k][live]), k
    assert lm.moving.sum() == 1 and lm.moving[remap[7]]
    assert len(lm.obs_kf) == len(before["obs_kf"])  # the dead had none left
    for i, (k, j) in enumerate(zip(lm.obs_kf, lm.obs_lm, strict=False)):  # each observation, now of the renumbered landmark
        o = obs_before[(int(k), int(live[j]))]
        for key in ("obs_uv", "obs_depth", "obs_octave"):
            assert np.array_equal(getattr(lm, key)[i], before[key][o]), key
    assert np.array_equal(lm.seen_by([2]), remap[[2, 9]])  # landmark 7 is moving
    assert lm.compact(force=True) is None  # nothing dead left


def test_compact_runs_by_itself_once_most_rows_are_dead(monkeypatch):
    from dynslam_cli.backend import landmarks

    monkeypatch.setattr(landmarks, "COMPACT_MIN_ROWS", 8)
    lm, ids = _map_with(10)
    lm.kill(np.arange(10) < 5)
    assert lm.compact() is None  # half dead: not more than half
    lm.kill(np.arange(10) < 6)
    assert lm.compact() is not None and len(lm) == 4
